"""The load path: stages of load steps, from load factor t = 0 to 1 in each.

Within a stage, prescribed displacements and term params are interpolated linearly from
their values at the stage start to the stage's targets. Each step is solved by Newton
(eyefem.solve.newton); a step that fails (diverges, inverts an element, produces
non-finite values) is cut in half and retried, and the increment grows back after easy
steps; after ``max_cuts`` cuts the solve stops with :class:`ConvergenceError`, which
carries the last converged state.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from typing import Any, Callable, Sequence

import jax
import numpy as np

from eyefem.solve.diagnosis import free_motions, limit_point, stiffness_spread
from eyefem.solve.assembly import Assembler
from eyefem.solve.model import Model, check_x64
from eyefem.solve.newton import newton
from eyefem.solve.options import NewtonOptions
from eyefem.solve.records import (
    ACCEPTED_FLAGS,
    ConvergenceError,
    Solution,
    StepFailed,
    StepRecord,
)

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class Stage:
    """One stage of a load path.

    Attributes:
      name: stage name (logs, outputs).
      n_steps: nominal number of load steps.
      prescribed: (dofs (n,), targets (n,)): displacement dofs prescribed during the
        stage and their values (mm) at its end, reached linearly from the start values.
      params: term name -> params at the end of the stage (linear ramp); others held.
      active: names of the terms in the energy (None: all).
      before: optional host-side hook ``f(model, q, theta) -> (model, q, theta)`` run at
        the stage start (closing a cavity, switching contact on...).
      duration: minutes the stage lasts (None: no time passes), for the terms that evolve
        in time (a cavity's volume regulation): each step lasts its share of it.
      times: step end times, minutes from the stage start (increasing, n_steps of them,
        the last one the duration): the steps land on them (a cut step is subdivided);
        None: n_steps equal steps.

    Terms with ``history_keys`` (a regulated FluidCavity) get each step's duration as
    their param ``dt`` (minutes), keep those keys from the last converged step instead of
    ramping them, and update them after it (``term.advance(q, params)``).
    """

    name: str
    n_steps: int
    prescribed: tuple[np.ndarray, np.ndarray]
    params: dict = dataclasses.field(default_factory=dict)
    active: tuple[str, ...] | None = None
    before: Callable | None = None
    duration: float | None = None
    times: tuple[float, ...] | None = None

    def __post_init__(self):
        if self.n_steps < 1:
            raise ValueError(f"stage '{self.name}': n_steps = {self.n_steps}; must be >= 1")
        if self.duration is not None and not (np.isfinite(self.duration) and self.duration >= 0):
            raise ValueError(f"stage '{self.name}': duration = {self.duration} min; must be >= 0")
        if self.times is not None:
            ts = np.asarray(self.times, np.float64).ravel()
            end = ts[-1] if len(ts) and self.duration is None else self.duration
            if (len(ts) != self.n_steps or not np.all(np.diff(np.r_[0.0, ts]) > 0)
                    or abs(ts[-1] - end) > 1e-12 * max(end, 1.0)):
                raise ValueError(f"stage '{self.name}': times = {ts.tolist()} min; expected "
                                 f"n_steps = {self.n_steps} increasing times > 0 ending at the "
                                 f"duration ({self.duration} min)")
            object.__setattr__(self, "times", tuple(ts.tolist()))
            object.__setattr__(self, "duration", float(ts[-1]))
        d, v = self.prescribed
        d = np.asarray(d, np.int64).ravel()
        v = np.broadcast_to(np.asarray(v, np.float64), d.shape).copy()
        if len(np.unique(d)) != len(d):
            raise ValueError(f"stage '{self.name}': a dof is prescribed twice")
        object.__setattr__(self, "prescribed", (d, v))


def interpolate(a, b, t):
    """The pytree (1 - t) a + t b (numpy leaves)."""
    return jax.tree_util.tree_map(lambda x, y: (1.0 - t) * np.asarray(x) + t * np.asarray(y), a, b)


def _timed(model: Model, th, theta, dt_min: float, active):
    """The step's theta: the history keys of the (active) time-dependent terms taken from
    the last converged theta (not ramped) and their step duration ``dt`` (minutes)."""
    for term in model.terms:
        keys = getattr(term, "history_keys", ())
        if keys and (active is None or term.name in active):
            th = {**th, term.name: {**th[term.name], **{k: theta[term.name][k] for k in keys},
                                    "dt": dt_min}}
    return th


def _advanced(model: Model, q, th, active):
    """theta after a converged step: each (active) time-dependent term's history moved on."""
    for term in model.terms:
        if getattr(term, "history_keys", ()) and (active is None or term.name in active):
            th = {**th, term.name: term.advance(q, th[term.name])}
    return th


def _with_history(model: Model, theta_end, theta):
    """A stage's end theta with the history keys of the time-dependent terms from theta."""
    for term in model.terms:
        keys = getattr(term, "history_keys", ())
        if keys:
            theta_end = {**theta_end, term.name: {**theta_end[term.name],
                                                  **{k: theta[term.name][k] for k in keys}}}
    return theta_end


def replay_hooks(model: Model, stages: Sequence[Stage], starts) -> Model:
    """The model after the ``before`` hooks of ``stages`` replayed with their start states
    ``starts`` ((q, theta) per stage, as a checkpoint holds them); the states are not
    re-solved (resuming a load path, rebuilding a completed stage's model)."""
    for (q_s, theta_s), stage in zip(starts, stages):
        if stage.before is not None:
            model, _, _ = stage.before(model, np.array(q_s), theta_s)
    return model


def solve(model: Model, stages: Sequence[Stage], *, q0=None, theta=None,
          options: NewtonOptions = NewtonOptions(),
          on_step: Callable[[StepRecord, Model, np.ndarray, Any], None] | None = None,
          on_stage_end: Callable[[int, Model, np.ndarray, Any, list], None] | None = None,
          completed: Sequence[tuple[np.ndarray, Any]] = ()) -> Solution:
    """Run a load path from q0 (default zero) with design theta (default model.theta0()).

    ``on_step(record, model, q, theta)`` is called after every converged step (outputs,
    progress; theta is the step's own: a time-dependent term's ``dt`` and the history it
    started from, see :class:`Stage`); ``on_stage_end(index, model, q, theta, starts)``
    after every completed stage, with ``starts`` the (q, theta) at the start of every stage so far (what a
    checkpoint needs). To resume, pass ``completed`` = those starts of the stages already
    done and q0/theta = the state at their end: their ``before`` hooks are replayed on
    the model (not re-solved) and the load path goes on with the next stage. Raises
    ConvergenceError with the last converged state on failure.
    """
    check_x64()
    if options.incompressibility == "augmented_lagrangian":
        from eyefem.fem.solid import SolidQ1P0
        from eyefem.solve.augmented import solve_augmented

        if any(isinstance(t, SolidQ1P0) for t in model.terms):  # (not yet transformed)
            return solve_augmented(model, stages, run=solve, q0=q0, theta=theta, options=options,
                                   on_step=on_step, on_stage_end=on_stage_end,
                                   completed=completed)
    q = np.zeros(model.n_dof) if q0 is None else np.array(q0, dtype=np.float64)
    theta = model.theta0() if theta is None else theta
    history: list[StepRecord] = []
    vref = float(sum(np.sum(t.data["dv"]) for t in model.terms if "dv" in t.data)) or 1.0
    asm, last_solver, stage = None, None, None
    starts = list(completed)
    model = replay_hooks(model, stages, completed)
    for i_stage, stage in enumerate(stages):
        if i_stage < len(completed):
            continue
        starts.append((q.copy(), theta))
        if stage.before is not None:
            model, q, theta = stage.before(model, q, theta)
        dofs, targets = stage.prescribed
        prescribed = np.zeros(model.n_dof, bool)
        prescribed[dofs] = True
        asm = Assembler(model, prescribed, beta=options.beta)
        start_vals = q[dofs].copy()
        theta_start = theta
        theta_end = dict(theta)
        for name, p in stage.params.items():
            model.term(name)
            theta_end[name] = {**theta[name], **p}
        marks = None if stage.times is None else np.asarray(stage.times) / stage.times[-1]

        def nominal(t):  # the nominal increment at load factor t
            if marks is None:
                return 1.0 / stage.n_steps
            k = min(int(np.searchsorted(marks, t + 1e-12)), len(marks) - 1)
            return marks[k] - (marks[k - 1] if k else 0.0)

        t, dt, step, cuts, step_refs, prev = 0.0, nominal(0.0), 0, 0, [], None
        tangent, previous = None, None  # the tangent predictor's factorisation, (theta, r)
        # not where contact is active: its forces switch with the state, and the old
        # tangent's step (blind to the contact the step makes) left coarse case 1's
        # tightening steps 3-4 iterations longer and took coarse case 2's encircled globe
        # to another, ovalised equilibrium (docs/formulation.md)
        predicts = options.tangent_predictor and not any(
            t.contact or t.dynamic for t in model.terms
            if stage.active is None or t.name in stage.active)
        path = [(0.0, q)]  # (load factor, state) of the stage's start and converged steps
        while t < 1.0 - 1e-12:
            t_new = min(1.0, t + dt)
            if marks is not None:  # land on the stage's step times
                t_new = min(t_new, float(marks[np.searchsorted(marks, t + 1e-12)]))
            th = interpolate(theta_start, theta_end, t_new)
            th = _timed(model, th, theta, (t_new - t) * (stage.duration or 0.0), stage.active)
            tic = time.perf_counter()
            fscale = float(np.median(step_refs)) if step_refs else 0.0
            starts_q = [q]
            if options.extrapolate and prev is not None:  # secant predictor along the path
                starts_q.insert(0, q + (q - prev[0]) * ((t_new - t) / (t - prev[1])))
            try:
                for k, q_start in enumerate(starts_q):
                    dqp = np.zeros(model.n_dof)
                    dqp[dofs] = start_vals + t_new * (targets - start_vals) - q_start[dofs]
                    try:
                        done = newton(model, asm, q_start, th, dqp, options, stage.active, vref,
                                      fscale, final=t_new >= 1.0 - 1e-12,
                                      predictor=tangent if k + 1 == len(starts_q) else None,
                                      previous=previous)
                        break
                    except StepFailed as exc:
                        if k + 1 == len(starts_q):
                            raise
                        log.debug("step from the extrapolated state failed (%s); retrying from "
                                  "the last converged state", exc)
            except StepFailed as exc:
                cuts += 1
                if cuts > options.max_cuts:
                    msg = (f"stage '{stage.name}': step to t = {t_new:.4g} failed after {cuts - 1} "
                           f"cuts (last increment {dt:.3g}): {exc}. The last converged state "
                           f"(t = {t:.4g}) is kept")
                    msg = " ".join([msg + "."] + _diagnosis(model, q, theta_start, theta_end, t,
                                                            prescribed, stage, path, exc))
                    log.error(msg)
                    raise ConvergenceError(msg, q, _with_history(
                        model, interpolate(theta_start, theta_end, t), theta), history) from None
                dt *= 0.5
                log.warning("stage '%s': step to t = %.4g failed (%s); cutting the increment to %.3g",
                            stage.name, t_new, exc, dt)
                continue
            step += 1
            step_refs.append(done.fref)
            prev = (q, t)
            t, q, model, its = t_new, done.q, done.model, done.iterations
            theta = _advanced(model, q, th, stage.active)
            path.append((t, q))
            # a factorisation that quasi-Newton steps moved away from (NewtonOptions.
            # quasi_newton) is no adjoint's: Solution.factorised takes the converged state's
            last_solver = None if getattr(done.solver, "stale", False) else done.solver
            if predicts and done.solver is not None:
                tangent = done.solver
            previous = (th, done.r) if done.r is not None else None
            rec = StepRecord(stage.name, step, t, its, done.residual, time.perf_counter() - tic,
                             {} if done.status.balanced else
                             {ACCEPTED_FLAGS[done.status]: True, "unbalanced_N": done.unbalanced_N})
            history.append(rec)
            log.info("stage %-12s step %3d  t = %.4f  iterations %2d  |r| = %.2e N of %.2e N "
                     "(%.2f s)", stage.name, step, t, its, done.residual, done.load_N, rec.wall)
            if on_step is not None:
                on_step(rec, model, q, th)
            if cuts and its <= options.grow_iterations:
                dt = min(nominal(t), dt * 2.0)
                cuts = max(cuts - 1, 0)
            elif not cuts and marks is not None and t < 1.0 - 1e-12:
                dt = nominal(t)
        theta = _with_history(model, theta_end, theta)
        if on_stage_end is not None:
            on_stage_end(i_stage, model, q, theta, starts)
    if asm is not None:
        asm.model = model
    return Solution(model, q, theta, history, asm, last_solver,
                    stage.active if stage is not None else None)


def _diagnosis(model, q, theta_start, theta_end, t, prescribed, stage, path, exc) -> list[str]:
    """Sentences on why a stage failed at load factor t (eyefem.solve.diagnosis); a
    diagnosis that itself fails is logged and left out, never masking the failure."""
    theta = interpolate(theta_start, theta_end, t)
    found = []
    for check in (lambda: free_motions(model, q, theta, prescribed, stage.active),
                  lambda: limit_point(path, stage),
                  lambda: stiffness_spread(model, theta) if "singular" in str(exc)
                  else ""):
        try:
            found.append(check())
        except Exception as err:  # noqa: BLE001 - a diagnosis must not hide the failure
            log.debug("failure diagnosis skipped: %r", err)
    return [f for f in found if f]
