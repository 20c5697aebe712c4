"""What a run of the main job leaves, as lines for the console: where each output is, and the
error history's latest rows."""

from __future__ import annotations

from pathlib import Path

from quadcore.identify import history
from quadcore.store import store


def outputs(root: Path) -> list[str]:
    """Where each stage writes under the data root ``root``."""
    return [
        "\nOutputs:",
        f"  decoded Parquet    {root / 'decoded'}/<event>/flight=<id>/data.parquet",
        f"  residual tables    {root / 'residuals'}/flight=<id>/data.parquet",
        f"  rollout errors     {root / 'rollouts'}/flight=<id>/data.parquet",
        f"  fitted model       {store.physics_model_path(root)}",
        f"  diagnosis report   {store.diagnosis_path(root).with_suffix('.html')} (and .md, .json)",
        f"  learned models     {store.learned_dir(root)}/<run>/ (model, scaler, features, manifest)",
        f"  learning report    {store.learning_report_path(root).with_suffix('.html')} (and .md, .json)",
        f"  flights as MCAP    {store.mcap_dir(root)}/<flight>.mcap (open in Foxglove)",
        f"  model as C         {store.export_c_dir(root)}/quadcore_model.{{h,c}} (for the flight controller)",
        f"  error history      {root / 'history'}/*.parquet",
    ]


def error_history(root: Path, last: int = 8) -> list[str]:
    """The error history's ``last`` rows (held-out RMSE per axis, and what each was scored on);
    nothing before the first diagnosis."""
    hist = history.read(root)
    if hist.height == 0:
        return []
    lines = ["\nError history (held-out residual RMSE, force N / torque mN m). Compare rows scored on the "
             "same flights only:"]
    for row in hist.tail(last).iter_rows(named=True):
        f = " ".join(f"{row[f'force_rmse_{a}_N']:.4f}" for a in "xyz")
        t = " ".join(f"{row[f'torque_rmse_{a}_Nm'] * 1e3:.4f}" for a in "xyz")
        n = len([x for x in row["eval_flights"].split(",") if x])
        scored = f"{row['eval_mode']} on {n} flight{'s' if n != 1 else ''}"
        lines.append(f"  {row['source']:<9} {row['model_label']:<40} {scored:<28} force {f}   torque {t}")
    return lines
