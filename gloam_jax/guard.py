"""Which model a run uses, and the guard that runs a safe variant where none fits the data.

``model: default`` picks the first shipped model (:data:`~gloam_jax.models.SHIPPED_MODELS`)
whose recorded sensors (:mod:`gloam_jax.sensor`) match the signature of the run's first scans.
Where none does, or where more than :data:`NOVELTY_SHARE` of those scans' points lie outside
the picked model's feature region (:mod:`gloam_jax.features.novelty`), the setting ``guard``
runs instead plain GICP (``gicp``), GICP with the model's learned association (``gicp_da``),
or the model all the same (``off``). A model named otherwise (a file, ``--weights``, ``net``)
is the user's choice: it runs, with a warning where its sensors or features do not fit.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import jax.numpy as jnp
import numpy as np

from gloam_jax.learned import METHODS
from gloam_jax.models import SHIPPED, SHIPPED_MODELS, GLOAMModel, load_model
from gloam_jax.odometry import OdometryConfig
from gloam_jax.sensor import SensorSignature, first_match, try_measure

# The share of the first scans' points outside the model's feature region beyond which the
# model is not trusted. The region holds 99 % of the training points (the quantile the
# novelty is fitted at), so 1 % lie outside on the training data itself; ten times that
# means whole structures (the ground, the walls) unlike any trained on, not stray points.
NOVELTY_SHARE = 0.10
DA_CANDIDATES = 5  # the association's candidates of gicp_da (configs/gicp_da.yaml)

Features = Callable[[GLOAMModel, int], np.ndarray]  # (model, k) -> scan k's raw features (N, D)


@dataclass(frozen=True)
class Choice:
    """The settings and model a run uses, what metrics.json records of the choice
    (``model``, ``method``, ``sensor``, ``decision``, ``reason``) and a warning, if any."""

    config: OdometryConfig
    model: GLOAMModel | None
    record: dict
    warning: str | None = None


def guarded(config: OdometryConfig, variant: str) -> OdometryConfig:
    """``config`` running the guard ``variant`` (``gicp`` or ``gicp_da``) instead."""
    if variant == "gicp":  # gicp.yaml's single nearest neighbour, no model
        gicp = dataclasses.replace(config.gicp, num_candidates=1)
        return dataclasses.replace(config, method="gicp", model=None, gicp=gicp)
    candidates = max(config.gicp.num_candidates, DA_CANDIDATES)
    gicp = dataclasses.replace(config.gicp, num_candidates=candidates)
    return dataclasses.replace(config, method="gicp_da", gicp=gicp)


def outside_share(model: GLOAMModel, raw: Sequence[np.ndarray]) -> float:
    """The share of points whose PCA features (from backbone features (N_k, D) of a few
    scans) lie outside ``model``'s feature region (the model must have one)."""
    f = jnp.asarray(model.pca_features(np.concatenate(raw)), jnp.float32)
    d2 = np.asarray(model.novelty.squared_distance(f))
    return float(np.mean(d2 > float(model.novelty.radius2)))


def _sensor_fit(model: GLOAMModel, sensor: SensorSignature | None) -> tuple[bool, str]:
    """Whether ``model`` records the scans' ``sensor``, and why (not)."""
    if sensor is None:
        return False, "the scans' sensor could not be measured"
    if model.sensors is None:
        return False, "the model records no training sensors (a file older than the record)"
    found, why = first_match(sensor, model.sensors)
    return found is not None, why


def choose(config: OdometryConfig, scans: Sequence[np.ndarray], features: Features) -> Choice:
    """The model (and settings) for a run whose first scans are ``scans`` (raw, (N, 3+));
    ``features`` gives a scan's backbone features for the novelty check."""
    if not any(METHODS[config.method]) or config.model is None:
        return Choice(config, None, {"model": None, "method": config.method})
    sensor = try_measure(scans)
    base = {"sensor": None if sensor is None else sensor.to_dict()}

    def record(model: str | None, cfg: OdometryConfig, decision: str, reason: str) -> dict:
        return {"model": model, "method": cfg.method, **base, "decision": decision,
                "reason": reason}  # fmt: skip

    def novel(model: GLOAMModel) -> str | None:
        base["outside_share"] = None
        if model.novelty is None:  # no region to be outside of: the scans' features unneeded
            return None
        share = outside_share(model, [features(model, k) for k in range(len(scans))])
        base["outside_share"] = share
        if share <= NOVELTY_SHARE:
            return None
        return (f"{100 * share:.0f} % of the first scans' points lie outside the model's "
                f"training features (more than {100 * NOVELTY_SHARE:.0f} %)")  # fmt: skip

    if config.model != SHIPPED:  # named by the user: it runs, with a warning
        model = load_model(config.model)
        fits, why = _sensor_fit(model, sensor)
        problem = None if fits else why
        problem = problem or novel(model)
        if problem is None:
            return Choice(config, model, record(config.model, config, "model", why))
        warning = f"model {config.model} forced: {problem}; it may do worse than plain GICP"
        return Choice(config, model, record(config.model, config, "forced", problem), warning)

    reasons = []
    for name in SHIPPED_MODELS:
        model = load_model(name)
        fits, why = _sensor_fit(model, sensor)
        reasons.append(f"{name}: {why}")
        if fits:
            problem = novel(model)
            if problem is None:
                return Choice(config, model, record(name, config, "model", f"{name}: {why}"))
            reasons[-1] = f"{name}: {problem}"
            break
    else:
        name, model = SHIPPED, load_model(SHIPPED)
    why = "; ".join(reasons)
    if config.guard == "off":
        warning = f"no shipped model fits ({why}); guard: off runs {name} all the same"
        return Choice(config, model, record(name, config, "guard off", why), warning)
    cfg = guarded(config, config.guard)
    kept = None if cfg.model is None else name
    return Choice(cfg, None if kept is None else model,
                  record(kept, cfg, f"guard: {config.guard}", why))  # fmt: skip
