"""A data root in an object store: ``s3://bucket/prefix`` through fsspec, against a real
S3-compatible server (moto's server mode) started on 127.0.0.1 by the test."""

from __future__ import annotations

import shutil

import dagster as dg
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from pipeline.assets import PER_FLIGHT
from pipeline.partitions import flights
from pipeline.resources import DataRoot, ModelConfig
from pipeline.run.parallel import range_tags
from quadcore.physics import decoded_store
from quadcore.sim import simulation
from quadcore.store import store
from quadcore.store.names import UnsafeNameError

moto_server = pytest.importorskip("moto.server", reason="moto[server] is a dev dependency")
pytest.importorskip("s3fs", reason="s3fs is a dev dependency")


@pytest.fixture(scope="module")
def s3_url():
    server = moto_server.ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1",
           "AWS_ENDPOINT_URL": f"http://{host}:{port}"}
    with pytest.MonkeyPatch.context() as mp:
        for k, v in env.items():
            mp.setenv(k, v)
        import s3fs  # type: ignore[import-untyped]

        s3fs.S3FileSystem.clear_instance_cache()
        s3fs.S3FileSystem(endpoint_url=env["AWS_ENDPOINT_URL"]).mkdir("lab")
        yield "s3://lab/quadcore"
    server.stop()


@pytest.mark.slow  # Dagster runs against an S3 server
def test_per_flight_stages_round_trip_through_s3(s3_url, tmp_path):
    raw = tmp_path / "raw"
    simulation.simulate_set(raw, [simulation.SimConfig(kind="random", duration_s=3.0, seed=s) for s in (41, 42)])
    data_root = DataRoot(root=s3_url, raw=str(raw))
    root = data_root.root_path
    assert store.is_remote(root) and str(root) == s3_url
    with dg.instance_for_test() as instance:
        instance.add_dynamic_partitions(flights.name, ["sim000", "sim001"])
        result = dg.materialize(PER_FLIGHT, instance=instance, tags=range_tags(["sim000", "sim001"]),
                                resources={"data_root": data_root, "model": ModelConfig()})
        assert result.success
    # Parquet: decoded and residual tables, read back from the server with their metadata
    assert store.decoded_flights(root, "fixedFrequency") == ["sim000", "sim001"]
    decoded = store.read_decoded(root, "fixedFrequency", "sim001")
    assert decoded.height > 1000 and "omega_b_x_radps" in decoded.columns
    assert store.read_metadata(store.decoded_path(root, "fixedFrequency", "sim001"))["flight"] == "sim001"
    provenance = decoded_store.recorded_provenance(root, "fixedFrequency", "sim001")
    assert provenance is not None and provenance.start_ns is not None
    assert provenance.source_sha256 == store.file_sha256(raw / "sim001")
    residual = store.read_table(root, "residuals", "sim000")
    assert residual.height == store.read_decoded(root, "fixedFrequency", "sim000").height
    assert store.read_metadata(store.table_path(root, "residuals", "sim000"))["model"]["label"] == "nominal"
    # JSON
    store.write_json({"flights": 2}, root / "reports" / "note.json")
    assert store.read_json(root / "reports" / "note.json") == {"flights": 2}
    # MCAP, read by the mcap reader straight from the object store
    with (root / "mcap" / "sim000.mcap").open("rb") as fh:
        reader = make_reader(fh, decoder_factories=[DecoderFactory()])
        first = next(reader.iter_decoded_messages(topics=["/pose"]))
        assert first[3].pose.position.z == pytest.approx(residual["p_w_z_m"][0], abs=1e-6)
    # nothing was written to the local disk in place of the bucket
    assert not any(p.name.startswith("s3") for p in tmp_path.iterdir())


@pytest.mark.slow  # the whole main job (every stage, learning included) against an S3 server
def test_the_main_job_runs_on_an_object_store(s3_url, drag_fleet, tmp_path, monkeypatch):
    """``python -m pipeline``'s stages with ``QUADCORE_DATA_ROOT=s3://...``: every output (decoded
    and residual Parquet, the fitted model, diagnosis and discovery JSON, reports, history,
    learned models, MCAP, C) is in the bucket, and nothing under the working directory."""
    from pipeline.run.main import run_all

    raw = tmp_path / "raw"
    raw.mkdir()
    for p in sorted(drag_fleet.iterdir()):
        if not p.name.endswith(".json"):
            shutil.copyfile(p, raw / p.name)
    monkeypatch.chdir(tmp_path)
    data_root = DataRoot(root=f"{s3_url}-job", raw=str(raw))
    root = data_root.root_path
    lines: list[str] = []
    with dg.instance_for_test() as instance:
        assert run_all(data_root, ModelConfig(effects="rotor_drag"), instance, log=lines.append) == 0, "\n".join(lines)
    ids = ["sim000", "sim001", "sim002", "sim003"]
    assert store.decoded_flights(root, "fixedFrequency") == ids
    fitted = store.read_json(store.physics_model_path(root))
    assert [e["name"] for e in fitted["effects"]] == ["rotor_drag"]
    assert store.read_metadata(store.table_path(root, "residuals", "sim003"))["model"]["label"] == fitted["label"]
    diagnosis = store.read_json(root / "reports" / "diagnosis.json")
    assert diagnosis["model"]["label"] == fitted["label"]
    assert "<html" in (root / "reports" / "diagnosis.html").read_text().lower()
    assert store.read_json(root / "reports" / "discovery.json")["effects_in_model"] == ["rotor_drag"]
    from quadcore.identify import binfile, history
    from quadcore.identify.diagnosis import rate_cache

    kept = binfile.decode(binfile.read_file(rate_cache.path(root, "sim003")))[0]  # the rate level's sums, kept
    assert kept["flight"] == "sim003" and kept["format"] == rate_cache.FORMAT

    assert history.read(root)["model_label"].to_list()[0] == fitted["label"]
    index = store.read_json(root / "learned" / "index.json")
    assert index["runs"] and store.read_json(root / "reports" / "learning.json")["holdout"] == "sim003"
    assert "QUADCORE_MODEL_H" in (root / "export_c" / "quadcore_model.h").read_text()
    with (root / "mcap" / "sim003.mcap").open("rb") as fh:
        summary = make_reader(fh).get_summary()
        assert summary is not None and summary.statistics.message_count > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["raw"]  # nothing written locally in its place
    with pytest.raises(UnsafeNameError):  # the data-root jail holds in the bucket too
        store.table_path(root, "residuals", "../../other-bucket")


@pytest.mark.slow  # an S3 server
def test_flight_statistics_round_trip_through_s3(s3_url, drag_fleet):
    """A flight's sufficient statistics written to the bucket in one PUT and read back whole,
    as the fleet fit reads them from an s3:// data root."""
    import numpy as np

    from quadcore.identify import flightdata
    from quadcore.identify.stats import sufficient
    from quadcore.logs import flight
    from quadcore.physics import vehicle

    veh = vehicle.load()
    fd = flightdata.flight_data("sim000", flight.decode_flight(drag_fleet / "sim000").tables["fixedFrequency"], veh)
    layout = sufficient.library_layout()
    s = sufficient.flight_stats(fd, veh, layout, sufficient.stats_key(veh, veh, layout))
    sufficient.save(s, s3_url)
    back = sufficient.load_current(s3_url, "sim000", s.key)
    assert back is not None and back.layout == s.layout and back.n == s.n
    np.testing.assert_array_equal(back.gram, s.gram)
    np.testing.assert_allclose(back.total, s.total, rtol=1e-12)


def test_a_data_root_in_an_object_store_has_its_own_model_file(s3_url, monkeypatch):
    """The data root's own ``model.toml`` (the demo writes one there) is the default model file
    in a bucket as on a disk; a plugin named by a relative path cannot be read from a bucket
    and is refused with the file and the reason."""
    from pipeline.resources import model_config_from_env
    from quadcore.spec.model import ModelFileError
    from quadcore.workflows import demo

    url = f"{s3_url}-own-model"
    demo.write_demo_model_file(url, "", ["rotor_drag", "thrust_scale"])
    monkeypatch.setenv("QUADCORE_DATA_ROOT", url)
    monkeypatch.delenv("QUADCORE_MODEL", raising=False)
    config = model_config_from_env()
    assert config.model_file == f"{url}/model.toml"
    spec = config.spec()
    assert spec.effects == ["rotor_drag", "thrust_scale"] and spec.source == f"{url}/model.toml"
    store.write_text('effects = []\nplugins = ["my_effect.py"]\n', store.own_model_file(url))
    with pytest.raises(ModelFileError, match="object store names local files by absolute path only"):
        model_config_from_env().spec()
