"""An effect: a named, documented augmentation of a stage's model.

A stage describes its model by a *spec* (any hashable value, usually a frozen dataclass
whose fields switch parts of the model on); an :class:`Effect` turns a spec into a richer
one.  The loop (:func:`bsipipe.loop.run_loop`) fits the richer model and keeps it only on
strong evidence.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Callable, Optional


@dataclass(frozen=True)
class Effect:
    """A model augmentation the loop may add.

    Attributes
    ----------
    name : str
        The contract's name (e.g. ``"viscoelastic-relaxation"``); the loop reports it.
    explanation : str
        The physics: what in the experiment produces this effect.
    signature : str
        What the effect leaves in the residual of a model that lacks it (which of the
        :func:`~bsipipe.loop.residual_structure` tests it trips, and how).
    apply : callable ``spec -> spec | None``
        The augmented spec; ``None`` (or the same spec) when the effect cannot augment
        ``spec`` any further (already present, at its maximum order, or not allowed).
    param_names : tuple of str
        Names of the parameters the effect adds (documentation; the report lists the
        parameters that actually appear).
    evidence : callable ``(before, after) -> dict | None``, optional
        Evidence from data outside the fitted residual (a side-camera width series for a
        boundary condition, say), given the loop states before and after the effect.  The
        dict must hold ``delta_bic`` (positive favours the effect) and may hold anything
        else worth reporting; ``None`` means there is no such data for this run.
    catch_all : bool
        A model-free correction (a smooth field fitted to the residual itself) that can absorb
        what a physical effect explains, and with it parameters the physical model identifies
        (a camera's principal point): the loop keeps it only in a round where no physical
        effect passes, so it takes what is left after them.

    Examples
    --------
    >>> from dataclasses import dataclass, replace
    >>> @dataclass(frozen=True)
    ... class Spec:
    ...     drift: bool = False
    >>> drift = Effect("drift", "sensor warms up", "residual correlates with time",
    ...                lambda s: None if s.drift else replace(s, drift=True), ("drift_per_s",))
    >>> drift.augment(Spec())
    Spec(drift=True)
    >>> drift.augment(Spec(drift=True)) is None
    True
    """

    name: str
    explanation: str
    signature: str
    apply: Callable[[Any], Any]
    param_names: tuple[str, ...] = ()
    evidence: Optional[Callable[[Any, Any], Optional[dict]]] = None
    catch_all: bool = False

    def augment(self, spec):
        """``apply(spec)``, or ``None`` when it leaves the spec unchanged."""
        new = self.apply(spec)
        if new is None or new == spec:
            return None
        return new

    def describe(self) -> dict:
        return {"name": self.name, "explanation": self.explanation, "signature": self.signature,
                "param_names": list(self.param_names)}
