"""What training minimises and what chooses the exported weights, from per-window errors.

``t_err``: the windows' mean translational relative error (a fraction), Eq. (8)'s loss.

``gicp_ratio``: each window's t_err divided by plain GICP's on the same registrations (its
``reference``, measured once), averaged, plus ``worse_penalty`` times the mean excess of the
windows made worse than GICP. Plain GICP scores 1. A model that halves one world's error while
doubling another's scores worse than one that leaves both alone: a learned method should fall
back to GICP where it has nothing to add, and an average of errors lets the hardest windows
(largest t_err) outvote the easy ones.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax.numpy as jnp
import numpy as np
from jax import Array
from jax.typing import ArrayLike

Objective = Literal["t_err", "gicp_ratio"]


def objective(
    t_err: ArrayLike, reference: ArrayLike | None = None, worse_penalty: float = 0.0
) -> Array:
    """Scalar objective of per-window errors ``t_err`` (W,): their mean without ``reference``,
    else the ``gicp_ratio`` of the module docstring with GICP's errors ``reference`` (W,)."""
    t_err = jnp.asarray(t_err)
    if reference is None:
        return jnp.mean(t_err)
    ratio = t_err / jnp.asarray(reference, t_err.dtype)
    return jnp.mean(ratio) + worse_penalty * jnp.mean(jnp.maximum(ratio - 1.0, 0.0))


class Score(NamedTuple):
    """Hard-association evaluation of some weights on a set of windows: the ``objective``
    value and the mean ``t_err`` (fraction) and ``r_err`` (rad/m), and per window
    ``windows_t_err`` (W,)."""

    objective: float
    t_err: float
    r_err: float
    windows_t_err: np.ndarray


def score(
    t_err: np.ndarray, r_err: np.ndarray, reference: np.ndarray | None, worse_penalty: float
) -> Score:
    """The :class:`Score` of per-window errors (W,) each."""
    value = float(objective(np.asarray(t_err, np.float64), reference, worse_penalty))
    return Score(value, float(np.mean(t_err)), float(np.mean(r_err)), np.asarray(t_err))
