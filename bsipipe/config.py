"""Typed, strictly validated configs.

Every config model derives from :class:`StrictModel`: an unknown key, a wrong type or a
missing required key is an :class:`~bsipipe.errors.InputError` (exit 2) that names the key
and the file.  The validated model, defaults filled in, is what goes into provenance.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError

from .errors import InputError

M = TypeVar("M", bound="StrictModel")


class StrictModel(BaseModel):
    """Base for every config: unknown keys and non-finite numbers (inf, nan) are rejected, values
    are validated on assignment."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


def _format_validation_error(err: ValidationError) -> tuple[str, str]:
    e = err.errors()[0]
    key = ".".join(str(p) for p in e.get("loc", ()))
    kind = e.get("type", "")
    if kind == "extra_forbidden":
        msg = "unknown key"
    elif kind == "missing":
        msg = "required key is missing"
    else:
        msg = e.get("msg", "invalid value")
        if "input" in e and not isinstance(e["input"], (dict, list)):
            msg += f" (got {e['input']!r})"
    more = len(err.errors()) - 1
    if more > 0:
        msg += f"; and {more} more problem{'s' if more > 1 else ''}"
    return key, msg


def validate(model: type[M], data: Any, source: str | os.PathLike | None = None) -> M:
    """Validate ``data`` (a dict) as ``model``; errors name the key and ``source``."""
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise InputError(f"expected a mapping of keys to values, got {type(data).__name__}", path=source)
    try:
        return model.model_validate(data)
    except ValidationError as err:
        key, msg = _format_validation_error(err)
        raise InputError(msg, path=source, key=key) from None


def load_yaml(path: str | os.PathLike) -> Any:
    """Read a YAML file; a missing file or a syntax error is an InputError naming file and line."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("file not found", path=path) from None
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(f"cannot read config: {e}", path=path) from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as e:
        line = getattr(getattr(e, "problem_mark", None), "line", None)
        raise InputError(f"invalid YAML: {getattr(e, 'problem', e)}", path=path,
                         line=None if line is None else line + 1) from None


def load_config(model: type[M], path: str | os.PathLike) -> M:
    return validate(model, load_yaml(path), source=path)


# --- fit-ogden ------------------------------------------------------------------------

ModelName = Literal["ogden", "ogden2", "ogden3", "neo-hookean", "mooney-rivlin"]
Mode = Literal["uniaxial", "equibiaxial", "pure-shear", "simple-shear"]
Boundary = Literal["frictionless", "no-slip"]


class FitConfig(StrictModel):
    """``bsipipe fit-ogden --config FILE``; command-line options win over these values."""

    diameter_mm: PositiveFloat | None = Field(None, description="specimen diameter (cylinder)")
    height_mm: PositiveFloat | None = Field(None, description="specimen height before contact")
    model: ModelName = "ogden"
    prony: int = Field(0, ge=0, le=3, description="number of Prony terms (hyperviscoelastic form)")
    boundary: Boundary = "frictionless"
    mode: Mode = "uniaxial"
    loop: bool = True
    max_strain: float | None = Field(None, gt=0, lt=1, description="fit only up to this nominal strain")
    bootstrap: int = Field(200, ge=0, description="bootstrap resamples that check the Jacobian intervals")
    seed: int = 0
