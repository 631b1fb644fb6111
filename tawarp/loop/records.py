"""The loop's records: a candidate scored by its linearized evidence, the counts of a
comparison, and the report (:class:`LoopReport`, report.json's fields as docs/loop.md lists
them). A refitted candidate model is :class:`tawarp.loop.evidence.Model`."""

from __future__ import annotations

import json
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field

import numpy as np

from ..fit.result import FitResult
from .evidence import Model


@dataclass
class Candidate:
    """A model scored at another model's solution by the quadratic model of the log
    posterior (:func:`tawarp.loop.evidence.linearized_evidence`): its ``effects`` (names,
    in the model's order), ``log_posterior`` (linearized ln Z + ln P(M)) and ``x``, the
    linearized optimum in the model's own parameter order (base, then each effect's): a
    start of its refit."""

    effects: tuple[str, ...]
    log_posterior: float
    x: np.ndarray


@dataclass
class ModelsCompared:
    """What a comparison did: ``subsets`` of the library within the size limit,
    ``linearized`` evaluations of the quadratic model (the base counted once), models
    ``refitted`` (the base included), and the effects left out as ``not_visible`` (their
    columns change the residual by less than the noise over their prior range)."""

    subsets: int
    linearized: int
    refitted: int
    not_visible: list[str] = field(default_factory=list)

    def to_json(self) -> dict:
        return {
            "subsets": self.subsets,
            "linearized": self.linearized,
            "refitted": self.refitted,
            "not_visible": list(self.not_visible),
        }


def parameter_report(f: FitResult, z: dict | None = None) -> dict:
    """{name: {value, std (None: undetermined), prior_z (shift from the prior in prior sds)}}."""
    z = z or {}
    return {
        k: {"value": v, "std": float(s) if np.isfinite(s) else None, "prior_z": z.get(k)}
        for (k, v), s in zip(f.value_dict().items(), f.std[0])
    }


def model_row(m: Model) -> dict:
    """A refitted model as report.json's ``model_probabilities`` lists it."""
    return {
        "effects": list(m.effects),
        "label": m.label,
        "probability": m.probability,
        "log_evidence": m.log_evidence,
        "log_model_prior": m.log_model_prior,
        "error": float(m.fit.rms_error[0]),
        "chi2": float(m.fit.cost[0]),
        "n_parameters": len(m.fit.names),
    }


def step_label(group: list[str]) -> str:
    """A claim's name in the report: the effect, or "A+B" for a group of effects that the
    data cannot tell apart (at least one of them is in the model)."""
    return "+".join(group)


@dataclass(eq=False)
class LoopReport(Mapping):
    """The loop's answer (:func:`tawarp.loop.run_loop`). Its fields are report.json's keys
    (docs/loop.md, "The report"), except these, derived from them: ``error_before`` and
    ``error_after``, ``accepted_steps``, ``chosen_effect``, ``best_model``,
    ``model_probabilities`` (the 20 most probable), ``group_probabilities``,
    ``supported_effects`` and ``indistinguishable``, ``parameters_before`` and
    ``parameters_after``, ``models_compared``, ``drift_before`` and ``drift_after`` (absent
    when ``drift`` is None: not computed) and ``comparison``/``comparison_note`` (absent when
    ``comparison`` is None).

    ``base`` is the base model, ``models`` the refitted models, most probable first (the
    base among them); ``accepted_groups`` every claim (one effect, or a group the data cannot
    separate); ``supported_alone``/``supported_groups`` what the comparison supports whether
    or not the checks let it be claimed; ``drift`` (before, after) or None.

    A read-only :class:`Mapping` of :meth:`as_dict` (report.json's keys, and ``_fits`` {before,
    after} and ``_models`` for figures and callers); :meth:`to_json` is report.json.
    """

    kind: str
    n_residuals: int
    verdict: str
    noise_floor: float | None
    noise_source: str
    base: Model
    models: list[Model]
    accepted_effects: list[str]
    accepted_groups: list[list[str]]
    chosen_description: str | None
    inclusion_probabilities: dict[str, float]
    group_probabilities: dict[str, float]
    supported_alone: list[str]
    supported_groups: list[list[str]]
    prior_tension: list[dict]
    counts: ModelsCompared
    goodness_of_fit_before: dict
    goodness_of_fit_after: dict
    unexplained_residual: dict | None
    base_parameters: list[str]
    pinned: list[str]
    #: {base parameter: [the model parameters it also sets]} (one material in two segments)
    ties: dict[str, list[str]]
    method: str
    residual_structure_before: dict
    residual_structure_after: dict
    next_measurement: list[dict]
    drift: tuple[dict | None, dict | None] | None = None
    comparison: dict | None = None
    comparison_note: str | None = None

    @property
    def best(self) -> Model:
        """The most probable model."""
        return self.models[0]

    @property
    def error_before(self) -> float:
        return float(self.base.fit.rms_error[0])

    @property
    def error_after(self) -> float:
        return float(self.best.fit.rms_error[0])

    @property
    def accepted_steps(self) -> list[str]:
        return [step_label(g) for g in self.accepted_groups]

    @property
    def chosen_effect(self) -> str | None:
        return self.accepted_effects[0] if self.accepted_effects else None

    def as_dict(self) -> dict:
        """report.json's fields in its order, with the private ``_fits`` and ``_models``
        (and the plans' arrays) that figures and callers read."""
        out = {
            "kind": self.kind,
            "n_residuals": self.n_residuals,
            "verdict": self.verdict,
            "noise_floor": self.noise_floor,
            "noise_source": self.noise_source,
            "error_before": self.error_before,
            "error_after": self.error_after,
            "accepted_effects": self.accepted_effects,
            "accepted_groups": self.accepted_groups,
            "accepted_steps": self.accepted_steps,
            "chosen_effect": self.chosen_effect,
            "chosen_description": self.chosen_description,
            "best_model": list(self.best.effects),
            "model_probabilities": [model_row(m) for m in self.models[:20]],
            "inclusion_probabilities": self.inclusion_probabilities,
            "group_probabilities": self.group_probabilities,
            "supported_effects": {"alone": self.supported_alone, "groups": self.supported_groups},
            "prior_tension": self.prior_tension,
            "models_compared": self.counts.to_json(),
            "goodness_of_fit_before": self.goodness_of_fit_before,
            "goodness_of_fit_after": self.goodness_of_fit_after,
            "unexplained_residual": self.unexplained_residual,
            "indistinguishable": self.supported_groups,
            "base_parameters": self.base_parameters,
            "pinned": self.pinned,
            "ties": self.ties,
            "method": self.method,
            "parameters_before": parameter_report(self.base.fit, self.base.z()),
            "parameters_after": parameter_report(self.best.fit, self.best.z()),
            "base_converged": bool(self.base.fit.converged[0]),
            "residual_structure_before": self.residual_structure_before,
            "residual_structure_after": self.residual_structure_after,
            "next_measurement": self.next_measurement,
        }
        if self.drift is not None:
            out["drift_before"], out["drift_after"] = self.drift
        out["_fits"] = {"before": self.base.fit, "after": self.best.fit}
        out["_models"] = self.models
        if self.comparison is not None:
            out["comparison"] = self.comparison
            out["comparison_note"] = self.comparison_note
        return out

    def to_json(self) -> dict:
        """report.json (before write_report adds ``figures``): :meth:`as_dict` without the
        private keys, at any depth, and with JSON types only."""
        return json.loads(json.dumps(_public(self.as_dict()), default=_json_default))

    def __getitem__(self, key: str):
        return self.as_dict()[key]

    def __iter__(self) -> Iterator[str]:
        return iter(self.as_dict())

    def __len__(self) -> int:
        return len(self.as_dict())


def _public(v):
    """``v`` without the keys that start with "_" (fits and arrays kept for the figures), at any depth."""
    if isinstance(v, dict):
        return {k: _public(x) for k, x in v.items() if not k.startswith("_")}
    if isinstance(v, list):
        return [_public(x) for x in v]
    return v


def _json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)
