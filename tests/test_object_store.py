"""A data root in an object store: ``s3://bucket/prefix`` through fsspec, against a real
S3-compatible server (moto's server mode) started on 127.0.0.1 by the test."""

from __future__ import annotations

import dagster as dg
import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory

from pipeline.definitions import PER_FLIGHT
from pipeline.main import range_tags
from pipeline.partitions import flights
from pipeline.resources import DataRoot, ModelConfig
from quadcore import simulation, store

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
    provenance = store.recorded_provenance(root, "fixedFrequency", "sim001")
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
