"""A model's own controller tuning: the contact controller's settings that stay tuned, chosen per model by
`python -m experiments calibrate --tune --model M --write` and written beside its scene file.

    tuning.save(model, fields, measured)      # <scene stem>.controller.json: the model's digest, the fields, the table
    tuning.load(model)                        # the fields (dict), {} where none; refused for another model
    tuning.config(model, "measured")          # PhysicsConfig.named(...) with the model's fields

What is derived from the model needs no tuning (the rotational gains' radius: half the tool's longest side,
`controller.rotation_radius`); what remains a constant chosen on the paper's hand is `TUNABLE`: the grip the force
solve prefers, the rotational damping's bound per tick, and the tool's pose-loop frequency. A file holds the
settings of one named controller (`config.CONTROLLERS`); the paper's controller is never tuned.
"""
from __future__ import annotations

import json
import math
import pathlib

from gsp_jax.physics.config import CONTROLLERS, DEFAULT_CONTROLLER, PhysicsConfig

TUNABLE = ("grip_force", "rotation_step", "tool_freq")  # the fields a model's tuning may set
SUFFIX = ".controller.json"


def path_of(model) -> pathlib.Path:
    """Where a model's tuning lives: beside its scene file, `<scene stem>.controller.json` (a `gsp_jax.Model`)."""
    return model.path.with_name(model.path.stem + SUFFIX)


def _check_fields(fields: dict, where: str) -> dict:
    """`fields` if every name is in `TUNABLE` and every value a finite number > 0 (and a valid `PhysicsConfig`),
    else ValueError naming `where`, the field and the value."""
    if not isinstance(fields, dict):
        raise ValueError(f"{where}: the fields must be a dict of {', '.join(TUNABLE)}, got {fields!r}")
    for name, value in fields.items():
        if name not in TUNABLE:
            raise ValueError(f"{where}: {name!r} is not a tunable controller field (tunable: {', '.join(TUNABLE)})")
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ValueError(f"{where}: {name} must be a finite number > 0, got {value!r}")
    PhysicsConfig().replace(**fields)  # the config's own checks
    return dict(fields)


def save(model, fields: dict, measured: dict | None = None, controller: str = DEFAULT_CONTROLLER,
         path: str | pathlib.Path | None = None) -> pathlib.Path:
    """Write the tuning of `model` (its name and digest, so another model's file is refused): `fields` (names in
    `TUNABLE`) for the named `controller`, and `measured` (what chose them: a JSON-able dict). Returns the path."""
    if controller not in CONTROLLERS or controller == "paper":
        raise ValueError(f"tuning: controller must be one of {sorted(set(CONTROLLERS) - {'paper'})} (the paper's "
                         f"controller is never tuned), got {controller!r}")
    path = path_of(model) if path is None else pathlib.Path(path)
    data = dict(model=model.name, digest=model.digest, controller=controller,
                fields=_check_fields(fields, str(path)), measured=measured or {})
    path.write_text(json.dumps(data, indent=1) + "\n")
    return path


def load(model, controller: str = DEFAULT_CONTROLLER, path: str | pathlib.Path | None = None) -> dict:
    """The tuned fields of `model` for the named `controller` ({} where there is no file, or it tunes another
    controller). ValueError naming the file where it was made for another model (name or digest) or is malformed."""
    path = path_of(model) if path is None else pathlib.Path(path)
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not a controller tuning (invalid JSON: {e})") from None
    if not isinstance(data, dict) or not {"model", "digest", "controller", "fields"} <= set(data):
        raise ValueError(f"{path}: not a controller tuning (it needs model, digest, controller and fields)")
    if data["model"] != model.name or data["digest"] != model.digest:
        raise ValueError(f"{path}: this controller tuning was made for model {data['model']!r} ({data['digest']}), "
                         f"not for {model.label}; rerun `python -m experiments calibrate --tune --model "
                         f"{model.path} --write`, or delete the file")
    if data["controller"] != controller:
        return {}
    return _check_fields(data["fields"], str(path))


def config(model, controller: str = DEFAULT_CONTROLLER, **changes) -> PhysicsConfig:
    """`PhysicsConfig.named(controller)` with `model`'s tuning for it (`load`; none for the paper's), then
    `changes`."""
    fields = {} if controller == "paper" else load(model, controller)
    return PhysicsConfig.named(controller, **{**fields, **changes})
