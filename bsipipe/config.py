"""Typed, strictly validated configs.

Every config model derives from :class:`StrictModel`: an unknown key, a wrong type or a
missing required key is an :class:`~bsipipe.errors.InputError` (exit 2) that names the key
and the file.  The validated model, defaults filled in, is what goes into provenance.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any, Literal, TypeVar, get_args, get_origin

import yaml
from pydantic import BaseModel, ConfigDict, Field, PositiveFloat, ValidationError, field_validator

from .errors import InputError

M = TypeVar("M", bound="StrictModel")


def _takes_bool(annotation) -> bool:
    """Whether a field's type admits a bool (``bool``, ``Any``, a ``Literal`` with ``True`` or
    ``False`` among its values, or a union / container with one)."""
    if annotation is bool or annotation is Any:
        return True
    if get_origin(annotation) is Literal:
        return any(isinstance(a, bool) for a in get_args(annotation))
    return any(_takes_bool(a) for a in get_args(annotation))


class StrictModel(BaseModel):
    """Base for every config: unknown keys, non-finite numbers (inf, nan) and ``true`` /
    ``false`` where a number belongs (pydantic's lax mode reads them as 1 and 0: YAML's
    ``height_mm: true`` would be a 1 mm specimen) are rejected; values are validated on
    assignment.  (A number written as a string, ``'18'`` or PyYAML's ``1e-3``, is read as
    the number.)"""

    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_a_number(cls, v, info):
        if isinstance(v, bool) and info.field_name in cls.model_fields:
            ann = cls.model_fields[info.field_name].annotation
            if not _takes_bool(ann):
                raise ValueError(f"expected {'a number' if _is_numeric(ann) else 'a value of its type'}, not true/false")
        if v is not None and not isinstance(v, bool) and info.field_name in cls.model_fields and _only_bool(
                cls.model_fields[info.field_name].annotation):
            # pydantic's lax mode reads "yes", "on", 1 as true: YAML's loop: "yes" (quoted) or 1
            raise ValueError(f"expected true or false, not {v!r}")
        return v


def _only_bool(annotation) -> bool:
    """Whether a field's type is ``bool`` (or ``bool | None``: None is let through)."""
    if annotation is bool:
        return True
    args = [a for a in get_args(annotation) if a is not type(None)]
    return get_origin(annotation) is not Literal and len(args) == 1 and args[0] is bool


def _is_numeric(annotation) -> bool:
    if annotation in (int, float):
        return True
    meta = get_args(annotation)
    return bool(meta) and any(_is_numeric(a) for a in meta)


#: pydantic's names of the alternatives it tried (``constrained-float``, ``literal['auto','none']``,
#: ``function-after[...]``, a bare ``float``), which it puts in an error's location among the keys
_ALTERNATIVE = re.compile(r"^(constrained-\w+|[a-z]+(-[a-z]+)*\[.*\]|str|int|float|bool|none|dict|list|tuple|set)$")


def _key_of(loc) -> str:
    """The config key of an error location, without pydantic's names of union alternatives:
    ``diameter_px.constrained-float`` is the key ``diameter_px``."""
    return ".".join(str(p) for p in loc if not (isinstance(p, str) and _ALTERNATIVE.match(p)))


def _format_validation_error(err: ValidationError) -> tuple[str, str]:
    e = err.errors()[0]
    key = _key_of(e.get("loc", ()))
    kind = e.get("type", "")
    if kind == "extra_forbidden":
        msg = "unknown key"
    elif kind == "missing":
        msg = "required key is missing"
    else:
        msg = e.get("msg", "invalid value")
        if kind == "value_error" and msg.startswith("Value error, "):
            msg = msg[len("Value error, "):]
        if "input" in e and not isinstance(e["input"], (dict, list)) and f"got {e['input']!r}" not in msg:
            msg += f" (got {e['input']!r})"
    rest = err.errors()[1:]
    if rest:
        # the others by key, not just counted (a list given for a text key fails each of its
        # alternative types: one key, several problems)
        keys = list(dict.fromkeys(_key_of(r.get("loc", ())) or "?" for r in rest))
        others = [k for k in keys if k != key]
        msg += (f"; and {len(rest)} more problem{'s' if len(rest) > 1 else ''}"
                + (f" (key{'s' if len(others) > 1 else ''} {', '.join(repr(k) for k in others)})" if others else
                   " with this key"))
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
        raise InputError(msg, path=source, key=key or None) from None  # a whole-model check: no key


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
        return yaml.load(text, Loader=_UniqueKeyLoader)
    except yaml.YAMLError as e:
        line = getattr(getattr(e, "problem_mark", None), "line", None)
        raise InputError(f"invalid YAML: {getattr(e, 'problem', e)}", path=path,
                         line=None if line is None else line + 1) from None


class _UniqueKeyLoader(yaml.SafeLoader):
    """YAML's safe loader that refuses a key given twice in one mapping (PyYAML keeps the last
    silently: ``diameter_mm: 18`` then ``diameter_mm: 20`` would fit with 20)."""

    def construct_mapping(self, node, deep=False):
        seen: dict = {}
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            try:
                first = seen.setdefault(key, key_node.start_mark.line)
            except TypeError:           # an unhashable key: the base class says so
                continue
            if first != key_node.start_mark.line:
                raise yaml.constructor.ConstructorError(
                    None, None, f"key {key!r} given twice (also line {first + 1})", key_node.start_mark)
        return super().construct_mapping(node, deep=deep)


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
    seed: int = Field(0, ge=0, description="seed of the bootstrap (a non-negative integer)")
