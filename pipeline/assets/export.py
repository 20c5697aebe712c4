"""Stage: a flight as MCAP for Foxglove (pose, IMU, motors, battery, model vs measured), and the
current model as C for the flight controller."""

import dagster as dg

from pipeline.assets.decode import MAIN_EVENT
from pipeline.assets.learning import learned_models
from pipeline.assets.model import RETRAIN, physics_model
from pipeline.assets.physics import residual_table
from pipeline.freshness import MODEL_VERSION, REFRESH, model_version
from pipeline.partitions import ONE_RUN, flights, for_each_flight
from pipeline.resources import DataRoot, ModelConfig
from quadcore.export import c as export_c, mcap as export
from quadcore.learn import learners
from quadcore.physics import decoded_store
from quadcore.store import store


@dg.asset(partitions_def=flights, backfill_policy=ONE_RUN, group_name="export", deps=[residual_table], kinds={"mcap"},
          automation_condition=REFRESH)
def flight_mcap(context: dg.AssetExecutionContext, data_root: DataRoot) -> dg.MaterializeResult:
    """`<root>/mcap/<flight>.mcap` per flight: open it in Foxglove (3D panel: the /tf frame 'body').
    Anchored at the start time recorded in the flight's decoded provenance."""
    root = data_root.root_path

    def work(fid):
        table = store.read_table(root, "residuals", fid)
        provenance = decoded_store.recorded_provenance(root, MAIN_EVENT, fid)
        if provenance is None or provenance.start_ns is None:
            raise dg.Failure(
                description=f"{fid}: no start time in its decoded provenance: re-materialise decoded_flight")
        path = store.mcap_path(root, fid)
        counts = export.write_mcap(table, path, provenance.start_ns,
                                   {"flight": fid, "start_source": provenance.start_source})
        used = store.read_metadata(store.table_path(root, "residuals", fid)).get("model", {})
        return {MODEL_VERSION: model_version(used), "messages": sum(counts.values()),
                "topics": dg.MetadataValue.json(counts),
                "path": dg.MetadataValue.path(str(path))}

    done = for_each_flight(context, work)
    return dg.MaterializeResult(metadata={"flights_in_run": len(done)})


class ExportCConfig(dg.Config):
    """``learned``: the learned part, the best run of this kind (``xgboost`` or ``mlp``), or ``none``."""

    learned: str = "xgboost"


@dg.asset(group_name="export", deps=[physics_model, learned_models], kinds={"c"}, automation_condition=RETRAIN)
def exported_model(context: dg.AssetExecutionContext, config: ExportCConfig,
                   data_root: DataRoot, model: ModelConfig) -> dg.MaterializeResult:
    """`<root>/export_c/quadcore_model.{h,c}`: the physics model's effects plus the best learned
    residual as self-contained C99 for the flight controller (see docs/how-to/firmware-export.md),
    checked with the strict C99 flags; the flash and RAM footprint in the metadata. An effect
    with no C form is left out, named with why (metadata ``left_out``, a warning, and the top of
    both files), rather than failing the run. Plugin effects come from the model file (its spec
    loads them), never from a path the saved model names."""
    root = data_root.root_path
    model.spec()
    try:
        exported = export_c.export(root, store.export_c_dir(root), config.learned, leave_out=True)
    except (export_c.ExportError, learners.LearningError) as exc:
        raise dg.Failure(description=str(exc)) from None
    left_out = exported.generated.left_out
    for _effect, why in left_out:
        context.log.warning(f"left out of the C model: {why}")
    metadata: dict[str, dg.RawMetadataValue] = {
        "model": exported.generated.label,
        "left_out": dg.MetadataValue.md("\n".join(f"- **{e}**: {why}" for e, why in left_out) or "none: every effect"),
        "header": dg.MetadataValue.path(str(exported.header)),
        "source": dg.MetadataValue.path(str(exported.source)),
        "inputs": dg.MetadataValue.json({f.name: f.logged_as() for f in exported.fields}),
        "footprint": dg.MetadataValue.md(exported.footprint.comment()) if exported.footprint else "not measured",
    }
    if exported.footprint:
        metadata.update(flash_bytes=exported.footprint.flash_bytes, ram_bytes=exported.footprint.ram_bytes)
    return dg.MaterializeResult(metadata=metadata)
