"""The extension the paper's conclusion asks for: gradients of the relative trajectory error
with respect to the MLP weights, through the GICP solves, with optax's Adam.

The loss is :func:`gloam_jax.training.batch.loss` (Eq. 8 over the training windows, frame-to-frame),
with the batch settings of the run: soft association gives the conversion MLP a gradient
through the choice among candidates; ``adjoint`` picks optimistix's unrolled
(``RecursiveCheckpointAdjoint``) or implicit (``ImplicitAdjoint``) differentiation of the LM
solves. With ``source_points``, each step sees a fresh random subset of every pair's source
points (seeded by the run's seed and the step, so a resumed run repeats them). Steps with a
non-finite loss or gradient are skipped. Every ``eval_every`` steps the
training loss is measured as TPE measures it (hard association), and on the validation windows
when the run has them; the best weights by the validation objective (else the training one)
are kept. Checkpoints are written atomically; a rerun in the same folder resumes, also
after Ctrl-C, which writes the last completed step before it propagates.

The registrations of a step are split over a device mesh (default: every local device, so
several GPUs share the pairs and one CPU changes nothing): see docs/scaling.md, "Sharding".
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import Mesh, NamedSharding
from jax.sharding import PartitionSpec as P

from gloam_jax import io
from gloam_jax.errors import InputError
from gloam_jax.interrupt import raise_if_stopped
from gloam_jax.learned import Learned
from gloam_jax.training import batch
from gloam_jax.training.problem import (
    Clock,
    Problem,
    choose,
    plot_objective,
    write_history,
)

CHECKPOINT = "checkpoint.npz"


def _rate(rate: float, warmup_steps: int) -> float | optax.Schedule:
    """``rate``, or step k's ``rate * min(1, k / warmup_steps)`` (k = 1, 2, ...)."""
    if warmup_steps == 0:
        return rate
    return lambda count: rate * jnp.minimum(1.0, (count + 1) / warmup_steps)


def _optimizer(problem: Problem) -> optax.GradientTransformation:
    cfg = problem.config.grad
    adam = optax.adam(_rate(cfg.learning_rate, cfg.warmup_steps))
    if cfg.head_learning_rate is not None:  # the backbone's last layer at its own rate

        def labels(p: Learned) -> Learned:
            mlps = jax.tree_util.tree_map(lambda _: "mlp", p._replace(head=None))
            return mlps._replace(head=jax.tree_util.tree_map(lambda _: "head", p.head))

        adam = optax.multi_transform(
            {"mlp": adam, "head": optax.adam(_rate(cfg.head_learning_rate, cfg.warmup_steps))},
            labels,
        )
    return optax.chain(optax.clip_by_global_norm(cfg.clip_norm), adam)


def save_checkpoint(path, trees: dict, meta: dict) -> None:
    """Pytrees (by name) and JSON metadata in one ``.npz``, atomically."""
    arrays = {}
    for name, tree in trees.items():
        for i, leaf in enumerate(jax.tree_util.tree_leaves(tree)):
            arrays[f"{name}_{i}"] = np.asarray(leaf)
    io.write_npz(path, meta=np.array(json.dumps(meta)), **arrays)


def load_checkpoint(path, templates: dict) -> tuple[dict, dict]:
    """Read :func:`save_checkpoint`'s file into the structures of ``templates``."""
    try:
        with np.load(path, allow_pickle=False) as z:
            meta = json.loads(str(z["meta"]))
            trees = {}
            for name, template in templates.items():
                leaves, treedef = jax.tree_util.tree_flatten(template)
                loaded = [z[f"{name}_{i}"] for i in range(len(leaves))]
                for old, new in zip(leaves, loaded, strict=True):
                    if np.shape(old) != new.shape:
                        raise ValueError(f"{name}: shape {new.shape}, expected {np.shape(old)}")
                typed = [
                    jnp.asarray(x, jnp.asarray(t).dtype)
                    for x, t in zip(loaded, leaves, strict=True)
                ]
                trees[name] = jax.tree_util.tree_unflatten(treedef, typed)
    # A truncated or damaged file (a copy cut short, a full disk) fails inside zipfile, zlib
    # or the npy reader: each is a file to delete, not a traceback.
    except (OSError, KeyError, ValueError, EOFError, zipfile.BadZipFile, zlib.error) as e:
        why = str(e) or type(e).__name__
        raise InputError(
            path, f"not a usable checkpoint of this run ({why}); delete it to start afresh"
        ) from None
    return trees, meta


def _finite(tree) -> jax.Array:
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in jax.tree_util.tree_leaves(tree)]))


def train_grad(
    problem: Problem,
    progress: Callable[[int, int, float], None] | None = None,
    mesh: Mesh | None = None,
):
    """Run (or resume) gradient training; export the best weights to ``RUN/model.npz``.

    ``progress(step, steps, best)`` after each step. Returns the exported model. Each step's
    registrations are split over ``mesh`` (default :func:`batch.pair_mesh`: every local
    device). On KeyboardInterrupt the last completed step is checkpointed, then it propagates.
    """
    cfg, run_dir = problem.config.grad, problem.run_dir
    mesh = batch.pair_mesh() if mesh is None else mesh
    replicated = NamedSharding(mesh, P())
    optimizer = _optimizer(problem)
    params = problem.init_params
    state = optimizer.init(params)
    best_params, best, best_t_err, history, step = params, np.inf, np.inf, [], 0
    clock = Clock()
    path = run_dir / CHECKPOINT
    if path.is_file():
        trees, meta = load_checkpoint(
            path, {"params": params, "state": state, "best_params": best_params}
        )
        params, state, best_params = trees["params"], trees["state"], trees["best_params"]
        step, best, history = meta["step"], meta["best"], meta["history"]
        best_t_err = meta.get("best_t_err", best)  # checkpoints before the objective setting
        clock = Clock(meta["elapsed"])
    # Weights and Adam's state on every device; the pairs split over them, once.
    params, state, best_params = jax.device_put((params, state, best_params), replicated)
    data, config = problem.data, problem.config.batch
    worse_penalty = problem.config.worse_penalty
    scans, pairs = batch.place(data.scans, data.pairs, mesh)
    head = jax.device_put(data.head, replicated)

    def loss(p: Learned, scans, pairs, head):
        step_data = batch.BatchData(scans, pairs, data.windows, data.regularizer, head)
        return batch.loss(p, step_data, config, mesh, problem.reference, worse_penalty)

    rows = data.pairs.rows.shape[1]
    subset = rows if cfg.source_points is None else min(cfg.source_points, rows)

    @jax.jit
    def update(p, s, scans, pairs, head, at):
        if subset < rows:  # the same random row slots of every pair (their rows are random)
            key = jax.random.fold_in(jax.random.PRNGKey(problem.config.seed), at)
            pairs = batch.select_rows(pairs, jax.random.permutation(key, rows)[:subset])
        value, grads = jax.value_and_grad(loss)(p, scans, pairs, head)
        ok = jnp.isfinite(value) & _finite(grads)
        grads = jax.tree_util.tree_map(lambda g: jnp.where(ok, g, 0.0), grads)
        updates, new_s = optimizer.update(grads, s, p)
        new_p = optax.apply_updates(p, updates)

        def keep(new, old):  # a skipped step leaves weights and Adam's moments as they were
            return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), new, old)

        new_p, new_s = keep(new_p, p), keep(new_s, s)
        return *jax.lax.with_sharding_constraint((new_p, new_s), replicated), value, ok

    def evaluate(p: Learned, at: int, soft: float | None) -> None:
        # The exported step is the best on the validation windows when there are any.
        nonlocal best, best_t_err, best_params
        train, val = problem.training_loss(p), problem.validation_loss(p)
        chosen = (train if val is None else val).objective
        if chosen < best:
            best, best_t_err, best_params = chosen, train.t_err, p
        history.append(
            {"step": at, "wall_s": clock.lap(), "objective": train.objective,
             "t_err": train.t_err, "r_err": train.r_err, "soft_loss": soft,
             **({} if val is None else {"val_objective": val.objective, "val_t_err": val.t_err}),
             "best": best, "best_t_err": best_t_err}
        )  # fmt: skip

    def checkpoint() -> None:
        meta = {"step": step, "best": best, "best_t_err": best_t_err, "history": history,
                "elapsed": clock.lap()}  # fmt: skip
        trees = {"params": params, "state": state, "best_params": best_params}
        save_checkpoint(path, trees, meta)
        write_history(run_dir, history)

    # What the last completed step left (its update, evaluation and checkpoint all done), as
    # one tuple, so that Ctrl-C arriving anywhere finds a consistent state to write.
    done = (step, params, state, best, best_t_err, best_params, len(history))
    try:
        # Trace and compile the update in a thread while the start is evaluated: XLA compiles
        # outside Python's lock, so the two overlap. A finished run compiles nothing.
        with ThreadPoolExecutor(1) as pool:
            compiling = (
                pool.submit(lambda: update.lower(params, state, scans, pairs, head, step).compile())
                if step < cfg.steps
                else None
            )
            if step == 0 and not history:
                evaluate(params, 0, None)
                done = (step, params, state, best, best_t_err, best_params, len(history))
            update_step = update if compiling is None else compiling.result()
        soft = None
        while step < cfg.steps:
            raise_if_stopped()
            params, state, value, ok = update_step(params, state, scans, pairs, head, step)
            soft = float(value) if bool(ok) else None
            step += 1
            clock.lap()
            if step % cfg.eval_every == 0 or step == cfg.steps:
                evaluate(params, step, soft)
            if step % cfg.checkpoint_every == 0 or step == cfg.steps:
                checkpoint()
            done = (step, params, state, best, best_t_err, best_params, len(history))
            if progress is not None:
                progress(step, cfg.steps, best_t_err)
    except KeyboardInterrupt:
        step, params, state, best, best_t_err, best_params, kept = done
        del history[kept:]
        checkpoint()
        raise
    write_history(run_dir, history)
    t_err, objective = {"t_err": "training (hard association)"}, {"objective": "training"}
    if problem.validation is not None:
        t_err["val_t_err"], objective["val_objective"] = "validation", "validation (worst root)"
    title = f"gradient ({config.gicp.adjoint} adjoint, {config.association} association)"
    plot_objective(problem, history, t_err, objective, f"{title}, {problem.config.method}")
    if not np.isfinite(best):
        raise InputError(run_dir, "training produced no finite loss")
    params, chosen = choose(problem, best_params, best, best_t_err)
    return problem.export(
        params, run_dir / "model.npz", {"steps": step, "wall_s": history[-1]["wall_s"], **chosen}
    )
