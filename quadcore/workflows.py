"""Steps the command line and the Dagster assets share, so both take the same decisions with
the same checks: which model (file, effects override) and which flights are held out.

The CLI keeps argument parsing and printing; an asset keeps loading, one call and metadata.
"""

from __future__ import annotations

from collections.abc import Iterable


class HoldoutError(ValueError):
    """A named held-out flight that is not among the flights (mistyped, or quarantined because
    its log could not be read), or a holdout that leaves nothing to fit on."""


def parse_names(text: str | None) -> list[str]:
    """``"a, b,,c"`` -> ``["a", "b", "c"]``: a comma-separated list as given on the command line
    or in an environment variable."""
    return [n.strip() for n in (text or "").split(",") if n.strip()]


def named_holdout(requested: list[str], flights: Iterable[str], where: str = "the flights") -> list[str]:
    """The requested held-out flights, checked against ``flights``.

    Raises :class:`HoldoutError` if one is not among them (it is never silently dropped: the
    scores would then be on other flights than the user asked for) or if every flight is held
    out. An empty request is returned as is (the caller picks its default)."""
    flights = list(flights)
    unknown = [h for h in requested if h not in flights]
    if unknown:
        raise HoldoutError(f"holdout flight(s) not found in {where}: {', '.join(unknown)} "
                           f"(a misspelt id, or a log that could not be read); flights: {', '.join(sorted(flights))}")
    if requested and not set(flights) - set(requested):
        raise HoldoutError("every flight is held out: nothing left to fit on")
    return list(requested)


def scored_flights(flights: Iterable[str], named: list[str], held_out: list[str]) -> tuple[list[str], list[str]]:
    """(the flights a diagnosis or discovery sees, the flights it scores on; empty: it
    cross-validates over the ones it sees).

    With a named holdout, every flight, scored on the named ones. Without, cross-validation
    over the flights the physics model is fitted on: ``held_out`` (the flight the learned
    models are scored on) is left out, so that no effect or term is chosen with it."""
    flights = list(flights)
    if named:
        return flights, list(named)
    return [f for f in flights if f not in held_out], []


def resolve_model(model_file: str | None, vehicle_name: str | None = None, thrust_map: str | None = None,
                  effects: list[str] | None = None):
    """The physics model a run asks for (a :class:`quadcore.model.ModelSpec`): a model file (its
    vehicle, effects, fixed parameters and plugins), else just the vehicle (``vehicle_name``:
    built-in name or file, default the Crazyflie 2.1); non-empty ``effects`` replace the effect
    list (keeping the file as the source); ``thrust_map`` overrides the vehicle's.

    Raises :class:`quadcore.model.ModelFileError`, :class:`quadcore.vehicle.VehicleFileError` or
    :class:`quadcore.effects.UnknownEffectError` with the reason."""
    from quadcore import model, vehicle

    if model_file:
        spec = model.load_model_file(model_file, vehicle_override=vehicle_name or None)
    else:
        spec = model.spec_from(vehicle.load(vehicle_name or None), [])
    if effects:
        spec = spec.with_effects(effects)
    if thrust_map:
        spec.vehicle = spec.vehicle.with_thrust_map(thrust_map)
    return spec
