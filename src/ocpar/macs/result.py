"""The result of a MACS run, as an object and as ``result.json``."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np

from ocpar.macs.local_search import STATIONARITY_TOL
from ocpar.models.labels import DIMENSIONLESS, Labels
from ocpar.results import Array, RunResult, array, components, text


def finite_or_none(values: np.ndarray) -> list[float | None]:
    """``values`` (1-D) as a JSON list, a non-finite entry (a failed refinement) as null."""
    return [float(v) if np.isfinite(v) else None for v in np.asarray(values, dtype=float)]


@dataclass
class MacsResult(RunResult):
    """Outcome of :func:`ocpar.macs.solve_macs`.

    ``front`` (k, m): the archive's objectives recomputed by integrating each member's control
    law accurately (sorted by J1); ``front_transcribed`` the DFET's own values; ``gd``, ``igd``
    of ``front`` against the problem's reference front (both normalised to the reference's
    ideal and nadir; None when the problem has no reference front); ``hv`` the hypervolume
    normalised by the reference front, or without one by the final front itself (None if that
    has no extent); ``decisions`` the members' decision vectors (controls and t_f);
    ``states`` (k, N, l+1, nx) each member's DFET state nodes per element (its trajectory,
    in the array file only) at ``state_fractions`` (N, l+1) of its t_f (the Gauss–Lobatto
    nodes: each element's first and last at its ends; :attr:`state_times` (k, N, l+1) the
    times); ``control_fractions`` (N (m+1),) the control nodes' times as fractions t/t_f of
    each member's t_f (the decision's controls at them, element by element); ``time_unit``,
    ``states_labels`` and ``controls_labels`` the model's units and names
    (:mod:`ocpar.models.labels`; None: the defaults), ``objective_units`` each objective's;
    ``objective_names`` m labels; ``reference_front`` the problem's (not written to JSON).
    After the final refinement (else None): per member whether its refinement was kept
    (``refined``, k), whether its point is one a neighbour's start reached (``moved``, k) and
    by how much that point dominates its own start's (``improvement``, k, Σ_i ΔJ_i/s_i in
    units of the archive's span), whether none of the starts of its last check beat it by
    more than the tolerance (``settled``, k), its Pareto-stationarity residual
    (``stationarity``, k) and trade-off weights (``tradeoff``, (k, m)); a member is
    :attr:`converged` when it is settled and its residual is ≤
    :data:`~ocpar.macs.local_search.STATIONARITY_TOL`; ``refinement_evaluations`` are
    included in ``evaluations``, ``refinement_rounds`` its rounds of checks and
    ``refinement_extra_evaluations`` the evaluations of those after the first (the re-checks
    of members that moved, :meth:`~ocpar.macs.algorithm.Macs.refine`). ``spread`` (None
    without the final placement, :meth:`~ocpar.macs.algorithm.Macs.spread`): its
    ``evaluations`` and targets ``placed`` (of ``targets``), and the transcribed front's
    ``gaps``, ``igd`` and ``floor`` (:func:`~ocpar.macs.metrics.spacing`).
    """

    scheme: ClassVar[str] = "macs"
    #: The front's quality: None in Python (the last iterate's in ``last_iterate``) and null
    #: in ``result.json`` unless the run converged.
    headline_fields: ClassVar[tuple[str, ...]] = ("gd", "igd", "hv")

    seed: int
    front: np.ndarray
    front_transcribed: np.ndarray
    decisions: np.ndarray
    states: np.ndarray
    state_fractions: np.ndarray
    evaluations: int
    iterations: int
    failed_searches: int
    gd: float | None
    igd: float | None
    hv: float | None
    settings: dict
    objective_names: list[str]
    reference_front: np.ndarray | None = None
    history: list[dict] = field(default_factory=list)
    refined: np.ndarray | None = None
    moved: np.ndarray | None = None
    improvement: np.ndarray | None = None
    settled: np.ndarray | None = None
    stationarity: np.ndarray | None = None
    tradeoff: np.ndarray | None = None
    refinement_evaluations: int = 0
    refinement_rounds: int = 0
    refinement_extra_evaluations: int = 0
    spread: dict | None = None
    control_fractions: np.ndarray | None = None
    time_unit: str = DIMENSIONLESS
    states_labels: Labels | None = None
    controls_labels: Labels | None = None
    objective_units: list[str] | None = None
    #: the common counts: every evaluation is one DFET solve; a failed search is rejected
    #: (the paper's penalty), never retried
    inner_solves: int = field(init=False)
    failed_solves: int = field(init=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        self.inner_solves = self.evaluations
        self.failed_solves = self.failed_searches

    @property
    def state_times(self) -> np.ndarray:
        """(k, N, l+1) each member's state nodes' times: its t_f times
        :attr:`state_fractions`."""
        return (np.asarray(self.decisions, float)[:, -1:, None]
                * np.asarray(self.state_fractions, float))

    def scheme_fields(self) -> dict:
        """MACS's fields of ``result.json``: the front and its quality (the decisions and
        trajectories are in the array file, :meth:`arrays`)."""
        return {
            "seed": self.seed,
            "objectives": self.objective_names,
            "front": np.asarray(self.front).tolist(),
            "front_transcribed": np.asarray(self.front_transcribed).tolist(),
            "evaluations": self.evaluations,
            "iterations": self.iterations,
            "failed_searches": self.failed_searches,
            "gd": self.gd,
            "igd": self.igd,
            "hv": self.hv,
            "settings": self.settings,
            "history": self.history,
            "spread": None if self.spread is None else {
                key: (np.asarray(value).tolist() if key == "gaps" else value)
                for key, value in self.spread.items()},
            "refinement": None if self.stationarity is None else {
                "evaluations": self.refinement_evaluations,
                "rounds": self.refinement_rounds,
                "extra_evaluations": self.refinement_extra_evaluations,
                "tolerance": STATIONARITY_TOL,
                "refined": np.asarray(self.refined).tolist(),
                "moved": np.asarray(self.moved).tolist(),
                "improvement": finite_or_none(self.improvement),
                "settled": np.asarray(self.settled).tolist(),
                "stationarity": finite_or_none(self.stationarity),
                "converged": self.converged.tolist(),
                "tradeoff": [finite_or_none(w) for w in self.tradeoff],
            },
        }

    def arrays(self) -> dict[str, Array]:
        """The array file's variables, per archive member (sorted by J1): the coordinates
        ``objective`` (the names, with ``objective_units``), ``state_component`` and
        ``control_component`` (the model's names, with their ``*_units``),
        ``control_fraction`` and ``state_fraction`` (the control nodes' and the state
        nodes' times as fractions of t_f, the same for every member); ``front`` (member,
        objective) re-simulated and ``front_transcribed``
        the DFET's; ``decision`` (member, decision_entry) the decision vector (control
        nodes, then t_f); ``final_time`` (member) t_f; ``control`` (member,
        control_fraction, control_component) the decision's controls at ``control_time``
        (member, control_fraction); ``state`` (member, state_fraction, state_component)
        the DFET trajectory at ``state_time`` (member, state_fraction), right-continuous
        (:func:`state_arrays`), with ``element_end_state`` (member, element,
        state_component) each element's own last node at ``element_end_fraction``
        (element); after the final refinement ``refined``, ``moved``, ``settled``,
        ``converged`` (int8 flags), ``improvement``, ``stationarity`` and ``tradeoff``
        (member, objective). Units: the problem's (:mod:`ocpar.models.labels`,
        :class:`~ocpar.macs.Objective`'s ``unit``)."""
        k, m = len(self.front), len(self.objective_names)
        decisions = np.asarray(self.decisions, float)
        if decisions.ndim != 2:
            decisions = decisions.reshape(k, -1)
        states = np.asarray(self.states, float)
        nx = states.shape[-1]
        fractions = (np.asarray(self.control_fractions, float)
                     if self.control_fractions is not None else None)
        state_labels = self.states_labels or Labels(
            tuple(f"x{i}" for i in range(nx)), (DIMENSIONLESS,) * nx)
        objectives = Labels(tuple(self.objective_names),
                            tuple(self.objective_units or (DIMENSIONLESS,) * m))
        t = self.time_unit
        out = {
            "objective": array("objective", text(objectives.names), "1", "objective names"),
            "objective_units": array("objective", text(objectives.units), "1",
                                     "units of each objective"),
            **components("state_component", state_labels, "state entry"),
            "front": array("member objective", np.reshape(self.front, (k, m)), objectives,
                           "objectives re-simulated from each member's control law"),
            "front_transcribed": array("member objective",
                                       np.reshape(self.front_transcribed, (k, m)), objectives,
                                       "objectives on the DFET transcription"),
            "decision": array("member decision_entry", decisions, "1",
                              "decision vector: control nodes, then t_f (each in its unit)"),
            "final_time": array("member", decisions[:, -1], t, "final time t_f"),
            **state_arrays(states, np.asarray(self.state_fractions, float), decisions[:, -1],
                           state_labels, t),
        }
        if fractions is not None:
            nu = (len(self.controls_labels.names) if self.controls_labels is not None
                  else (decisions.shape[1] - 1) // fractions.size)
            control_labels = self.controls_labels or Labels(
                tuple(f"u{i}" for i in range(nu)), (DIMENSIONLESS,) * nu)
            out |= {
                "control_fraction": array("control_fraction", fractions, "1",
                                          "time of each control node as a fraction of t_f"),
                **components("control_component", control_labels, "control entry"),
                "control": array("member control_fraction control_component",
                                 decisions[:, :-1].reshape(k, fractions.size, nu),
                                 control_labels, "control nodes (the member's control law)",
                                 coordinates="control_time"),
                "control_time": array("member control_fraction",
                                      decisions[:, -1:] * fractions, t,
                                      "time of each control node"),
            }
        if self.stationarity is not None:
            flags = {"refined": "its refinement was kept",
                     "moved": "its point is one a neighbour's start reached",
                     "settled": "no start of its last check beat it by more than the tolerance",
                     "converged": "settled and Pareto-stationary within the tolerance"}
            out |= {name: array("member", np.asarray(getattr(self, name), np.int8), "1",
                                f"1: {words}") for name, words in flags.items()}
            out |= {
                "improvement": array("member", np.asarray(self.improvement, float), "1",
                                     "sum_i dJ_i/s_i by which the point dominates its own "
                                     "start's (units of the archive's span)"),
                "stationarity": array("member", np.asarray(self.stationarity, float), "1",
                                      "Pareto-stationarity residual",
                                      tolerance=STATIONARITY_TOL),
                "tradeoff": array("member objective", np.reshape(self.tradeoff, (k, m)), "1",
                                  "trade-off weights"),
            }
        return out

    @property
    def converged(self) -> np.ndarray | None:
        """Per member (k,): settled (no neighbour's start beat it) and its stationarity
        residual within the tolerance (None without the refinement)."""
        if self.stationarity is None:
            return None
        return np.asarray(self.settled, dtype=bool) & (np.asarray(self.stationarity)
                                                       <= STATIONARITY_TOL)

    def summary(self) -> str:
        return (
            f"status {self.status}{f' ({self.message})' if self.message else ''}: "
            f"{len(self.front)} archive members after {self.evaluations} "
            f"evaluations, {self.iterations} iterations, {self.supersteps} supersteps "
            f"({self.failed_searches} infeasible searches rejected)\n"
            f"{self.placement()}{self.refinement()}"
            f"{self.quality()}{self.hv_scale()}\n"
            f"wall time {self.wall_time_s:.2f} s on {self.workers} {self.backend} worker(s)"
        )

    def hv_scale(self) -> str:
        """What HV is measured in, for the summary: each objective scaled to ideal 0 and nadir
        1 (of the reference front, or the front found), up to the reference point 1.1 in
        each, so the ideal point alone would give 1.1^m (1.21 for two objectives) and a good
        front exceeds 1."""
        if self.hv is None:
            return ""
        m = len(self.objective_names)
        box = "reference front's" if self.reference_front is not None else "front's own"
        return (f"   (HV of the objectives scaled to the {box} ideal 0 and nadir 1, up to "
                f"1.1 in each: the ideal point would give 1.1^{m} = {1.1 ** m:.4g})")

    def placement(self) -> str:
        """The final placement as one line (empty without it)."""
        if self.spread is None:
            return ""
        igd, floor = self.spread["igd"], self.spread["floor"]
        return (f"placement: {self.spread['placed']} of {self.spread['targets']} targets "
                f"reached, {self.spread['evaluations']} of the evaluations; spacing IGD "
                f"{igd:.4g} against {floor:.4g}, the floor estimated from the members "
                f"({100 * (igd / floor - 1):+.1f} %)\n")

    def refinement(self) -> str:
        """The final refinement as one line (empty without it)."""
        if self.stationarity is None:
            return ""
        moved = np.asarray(self.moved, dtype=bool)
        by = (f" (by {np.min(self.improvement[moved]):.1e} to "
              f"{np.max(self.improvement[moved]):.1e} of the span)" if moved.any() else "")
        return (f"refinement: {int(np.sum(self.refined))} of {len(self.front)} members refined, "
                f"{int(moved.sum())} moved by a neighbour's start{by}, "
                f"{int(np.sum(self.converged))} converged (settled, stationary to "
                f"{STATIONARITY_TOL:g}; largest residual "
                f"{np.max(self.stationarity, initial=0.0):.1e}), "
                f"{self.refinement_evaluations} of the evaluations in "
                f"{self.refinement_rounds} rounds ({self.refinement_extra_evaluations} after "
                f"the first)\n")

    def headline_title(self) -> str:
        """The front's quality, for the plots' titles (:meth:`~ocpar.results.RunResult.title`)."""
        return self.quality()

    def quality(self) -> str:
        """GD, IGD (when known) and HV as one line; 'not reached (…)' unless converged."""
        if self.status != "converged":
            return f"GD, IGD, HV {self.not_reached()}"
        figures = [f"{name} {value:{fmt}}" for name, value, fmt in
                   (("GD", self.gd, ".3e"), ("IGD", self.igd, ".3e"), ("HV", self.hv, ".6f"))
                   if value is not None]
        return "   ".join(figures) or "no quality figures (no reference front)"


def state_arrays(states: np.ndarray, fractions: np.ndarray, final_times: np.ndarray,
                 labels: Labels, time_unit: str) -> dict[str, Array]:
    """The array file's variables of the members' DFET states ``states`` (k, N, l+1, nx) at
    ``fractions`` (N, l+1) of their ``final_times`` (k,). DFET's states are discontinuous
    across elements (each element its own polynomial, its first and last node at its ends),
    so a time t_j = j t_f/N between elements has two values; ``state`` (member,
    state_fraction, state_component) is right-continuous, as a control on ``interval_time``
    is: at each element's nodes but its last, and t_f (the last element's last node), so that
    ``state_fraction`` (N l + 1,) is a 1-D coordinate (``state.sel(state_fraction=0.5,
    method="nearest")``) with ``state_time`` (member, state_fraction) each member's times;
    ``element_end_state`` (member, element, state_component) every element's own last node
    (the left limit at ``element_end_fraction`` (j+1)/N; its jump to ``state`` there is the
    transcription's discontinuity)."""
    k, n, nodes, nx = states.shape
    inner = states[:, :, :-1].reshape(k, n * (nodes - 1), nx)
    state = np.concatenate([inner, states[:, -1, -1:]], axis=1)
    fraction = np.concatenate([fractions[:, :-1].ravel(), fractions[-1, -1:]])
    return {
        "state_fraction": array("state_fraction", fraction, "1",
                                "time of each state node as a fraction of t_f"),
        "state": array("member state_fraction state_component", state, labels,
                       "DFET state nodes (the member's trajectory; right-continuous at "
                       "the elements' ends)", coordinates="state_time"),
        "state_time": array("member state_fraction", final_times[:, None] * fraction,
                            time_unit, "time of each state node"),
        "element_end_fraction": array("element", fractions[:, -1], "1",
                                      "each element's end as a fraction of t_f"),
        "element_end_state": array("member element state_component", states[:, :, -1],
                                   labels, "each element's own state at its end (the left "
                                   "limit there)", coordinates="element_end_fraction"),
    }
