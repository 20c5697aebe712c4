"""The error history compares like with like: one series per evaluation set, a row only when
the model or the flights changed, a step chart per series."""

from __future__ import annotations

import io

from PIL import Image

from quadcore.identify import history
from quadcore.report import diagnosis as diagnosis_report


def _record(root, label, force_x, flights, mode="holdout", params=None):
    return history.record(root, "diagnosis", label, [force_x, 0.01, 0.02], [1e-4, 2e-4, 3e-4],
                          eval_mode=mode, eval_flights=flights, parameters=params or {})


def test_unchanged_models_add_no_row_and_sets_are_separate_series(tmp_path):
    assert _record(tmp_path, "nominal", 0.014, ["jana02"]) is not None
    assert _record(tmp_path, "nominal", 0.014, ["jana02"]) is None  # same model, same flight: nothing new
    assert _record(tmp_path, "nominal", 0.020, ["a", "b", "c"], mode="cross-validation") is not None
    assert _record(tmp_path, "nominal+rotor_drag", 0.0005, ["jana02"], params={"k": 0.12}) is not None
    assert _record(tmp_path, "nominal+rotor_drag", 0.0005, ["jana02"], params={"k": 0.13}) is not None  # refit
    assert _record(tmp_path, "nominal", 0.014, ["jana02"]) is not None  # back to nominal: a change again
    sets = history.series(history.read(tmp_path))
    assert list(sets) == ["holdout on jana02", "cross-validation on 3 flights"]  # most recent first
    assert sets["holdout on jana02"]["model_label"].to_list() == [
        "nominal", "nominal+rotor_drag", "nominal+rotor_drag", "nominal"]
    assert sets["cross-validation on 3 flights"].height == 1


def test_history_plot_has_a_row_of_panels_per_set_and_the_table_states_units(tmp_path):
    _record(tmp_path, "nominal", 0.014, ["jana02"])
    _record(tmp_path, "nominal", 0.020, ["a", "b", "c"], mode="cross-validation")
    _record(tmp_path, "nominal+rotor_drag", 0.0005, ["jana02"])
    hist = history.read(tmp_path)
    one = Image.open(io.BytesIO(diagnosis_report.history_plot(hist.filter(hist["eval_mode"] == "holdout"))))
    two = Image.open(io.BytesIO(diagnosis_report.history_plot(hist)))
    assert two.size[1] > 1.6 * one.size[1]  # a second row of panels for the second set
    table = diagnosis_report.history_table(hist)
    assert "torque_rmse_x_mNm" in table.columns and table["torque_rmse_x_mNm"].to_list() == [0.1, 0.1, 0.1]
    assert table["evaluation_set"].to_list() == ["holdout on jana02", "cross-validation on 3 flights",
                                                 "holdout on jana02"]


def test_a_history_plot_is_drawn_once_per_history(tmp_path):
    """The report and the error_history asset show the same history: the second asks for a plot
    already drawn and gets it without drawing; another history is drawn anew."""
    _record(tmp_path, "nominal", 0.014, ["jana02"])
    first = diagnosis_report.history_plot(history.read(tmp_path))
    assert diagnosis_report.history_plot(history.read(tmp_path)) is first  # an equal table read again
    _record(tmp_path, "nominal+rotor_drag", 0.0005, ["jana02"])
    changed = diagnosis_report.history_plot(history.read(tmp_path))
    assert changed != first
