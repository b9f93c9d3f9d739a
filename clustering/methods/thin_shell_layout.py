"""Le, Zhu & Deng (2013): choose the markers from which a thin-shell surface best follows the data.

Reconstruction ``X' = W·X[H]`` with ``W = Â⁻¹B̂`` (:mod:`mocaptk.thin_shell`): every vertex moves
as the thin shell pinned at the markers ``H``. Block coordinate descent, one marker at a time:
the expected trajectory of marker j is ``H̄j = Wjᵀ·Rj / (Wjᵀ·Wj)`` (``Rj`` = data minus the other
markers' contribution); the marker moves to the vertex whose trajectory is closest to ``H̄j``;
``W`` is updated; sweeps repeat until no marker moves. Random restarts keep the best layout.

**Factorization reuse.** ``A`` is factored once (sparse Cholesky, CHOLMOD via cholespy, of
``K = A + ρ·U·Uᵀ``, ``U`` one anchor vertex per connected component, which removes the null
space of translations). For any marker set, ``W`` follows exactly from the columns ``K⁻¹e_h`` of
the markers plus an (M + c)-sized dense system (a Schur-complement / capacitance solve, see
:meth:`ThinShellWeights.weights`), and the reconstruction error from entries of ``K⁻¹`` and
``K⁻²`` and rows of ``K⁻¹X`` (:meth:`ThinShellWeights.error`, no V-length work). Trying a
vertex costs one pair of triangular solves the first time and none after — never a
refactorization.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Sequence
from dataclasses import dataclass

import cholespy
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from mocaptk.errors import MocaptkError, OptionError
from mocaptk.thin_shell import thin_shell_operator
from mocaptk.threads import single_threaded

from .problem import LayoutProblem


def _cholesky(matrix: sp.spmatrix) -> cholespy.CholeskySolverD:
    """Sparse Cholesky factor (CHOLMOD via cholespy) of a symmetric positive definite matrix."""
    coo = sp.coo_matrix(matrix)
    try:
        return cholespy.CholeskySolverD(coo.shape[0], coo.row.astype(np.int32), coo.col.astype(np.int32),
                                        coo.data.astype(np.float64), cholespy.MatrixType.COO)
    except ValueError as exc:  # not positive definite
        raise MocaptkError("the thin-shell operator is singular beyond translations "
                           "(degenerate triangles or duplicate vertices in the mesh?)") from exc


@dataclass(eq=False)
class ThinShellWeights:
    """Interpolation weights of the thin shell for any marker set, from one factorization.

    ``W`` minimizes ``xᵀAx`` per column subject to ``x[markers] = I``. With ``A = K − ρ·U·Uᵀ``:
    ``x = K⁻¹Pᵀλ + ρ·K⁻¹U·s``; the (M + c) unknowns ``λ, s`` solve ``P·x = I`` and ``Uᵀx = s``.
    Components of the mesh without a marker keep weight 0 (they stay at rest).

    Everything :meth:`error` needs is an entry of ``K⁻¹`` or ``K⁻²`` between markers, a row of
    ``K⁻¹X`` or of ``K⁻¹U``, ``K⁻²U``: layout markers keep their columns ``g = K⁻¹e_v`` and
    ``h = K⁻¹g`` ("resident"), so a trial vertex v needs only row v of them plus its own
    entries ``K⁻¹[v, v]``, ``K⁻²[v, v]`` (cached per vertex once solved: a vertex tried again
    costs no solve). ``solves`` counts triangular solve pairs (one per right-hand side).
    """

    operator: sp.spmatrix
    solves: int = 0
    evaluations: int = 0

    def __post_init__(self) -> None:
        op = sp.csr_matrix(self.operator)
        n = op.shape[0]
        n_comp, comp = connected_components(op, directed=False)
        anchors = np.array([int(np.flatnonzero(comp == c)[0]) for c in range(n_comp)])
        diag = op.diagonal()
        self.rho = float(diag[diag > 0].mean()) if (diag > 0).any() else 1.0
        basis = sp.csr_matrix((np.ones(n_comp), (anchors, np.arange(n_comp))), shape=(n, n_comp))
        self.component = comp
        self.anchors = anchors
        self._factor = _cholesky(op + self.rho * (basis @ basis.T))
        self._anchor_green = self._solve(basis.toarray())  # K⁻¹U (V, c)
        self._setup_solves = self.solves
        self._reset()

    def fresh(self) -> ThinShellWeights:
        """A solver with this one's operator and factorization and nothing else (no resident
        columns, cached entries or bound data): as if built anew, without refactoring."""
        other = copy.copy(self)
        other.solves, other.evaluations = self._setup_solves, 0
        other._reset()
        return other

    def _reset(self) -> None:
        n = self._anchor_green.shape[0]
        self._slot_of = np.full(n, -1, dtype=np.intp)  # resident vertex -> its column in _g / _h
        self._members: list[int] = []  # resident vertices by column
        self._g = np.empty((n, 0))  # K⁻¹e_v of the resident vertices
        self._h = np.empty((n, 0))  # K⁻²e_v (solved when first needed, batched with candidates)
        self._has_h = np.zeros(0, dtype=bool)
        self._entries: dict[tuple[int, int], tuple[float, float]] = {}  # (K⁻¹, K⁻²) of vertex pairs
        self._last_batch: dict[int, np.ndarray] = {}  # columns of the latest prepare()
        self._layouts: dict[bytes, _LayoutBlocks] = {}  # per layout of the current sweep

    def _solve(self, rhs: np.ndarray) -> np.ndarray:
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        out = np.empty_like(rhs)
        self._factor.solve(rhs, out)
        self.solves += rhs.shape[1]
        return out

    def _resident(self, vertices: Sequence[int]) -> np.ndarray:
        """Column slots of ``vertices``, solving ``K⁻¹e_v`` for the new ones together."""
        vertices = np.asarray(vertices, dtype=np.intp)
        missing = [v for v in dict.fromkeys(vertices.tolist()) if self._slot_of[v] < 0]
        if missing:
            count, n = len(self._members), self._g.shape[0]
            if count + len(missing) > self._g.shape[1]:
                capacity = max(2 * self._g.shape[1], count + len(missing), 64)
                for name in ("_g", "_h"):
                    grown = np.empty((n, capacity))
                    grown[:, :count] = getattr(self, name)[:, :count]
                    setattr(self, name, grown)
                self._has_h = np.concatenate([self._has_h[:count], np.zeros(capacity - count, dtype=bool)])
            unsolved = [v for v in missing if v not in self._last_batch]
            rhs = np.zeros((n, len(unsolved)))
            rhs[unsolved, np.arange(len(unsolved))] = 1.0
            solved = dict(zip(unsolved, self._solve(rhs).T)) if unsolved else {}
            for k, v in enumerate(missing, start=count):
                self._g[:, k] = solved[v] if v in solved else self._last_batch[v]
                self._has_h[k] = False
                self._slot_of[v] = k
                self._members.append(v)
        return self._slot_of[vertices]

    def _complete_h(self, extra: np.ndarray | None = None) -> np.ndarray | None:
        """Solve the missing ``K⁻²e_v`` of resident vertices, together with the right-hand sides
        ``extra`` (returns their solutions)."""
        lacking = np.flatnonzero(~self._has_h[:len(self._members)])
        width = 0 if extra is None else extra.shape[1]
        if not lacking.size and not width:
            return None
        rhs = np.empty((self._g.shape[0], width + lacking.size))
        if width:
            rhs[:, :width] = extra
        rhs[:, width:] = self._g[:, lacking]
        out = self._solve(rhs)
        self._h[:, lacking] = out[:, width:]
        self._has_h[lacking] = True
        return out[:, :width]

    def forget(self, keep: Sequence[int]) -> None:
        """Drop resident columns except those of ``keep`` (bounds memory over long optimizations)."""
        kept = [v for v in dict.fromkeys(int(v) for v in keep) if self._slot_of[v] >= 0]
        old = self._slot_of[kept]
        self._g[:, :old.size] = self._g[:, old]
        self._h[:, :old.size] = self._h[:, old]
        self._has_h[:old.size] = self._has_h[old]
        self._slot_of[self._members] = -1
        self._slot_of[kept] = np.arange(len(kept))
        self._members = kept
        self._last_batch = {}
        self._layouts.clear()

    def _cached(self, vertices: Sequence[int]) -> bool:
        return all((min(v, w), max(v, w)) in self._entries for v in vertices for w in vertices)

    def prepare(self, groups: Sequence[Sequence[int]]) -> None:
        """Make trial layouts that differ from resident markers by one group each (a moved unit)
        cheap: the ``K⁻¹`` and ``K⁻²`` entries among each group's non-resident vertices, solved
        for all groups in one multi-right-hand-side solve (with any missing ``K⁻²e_v`` of
        resident vertices)."""
        todo = [new for new in ([int(v) for v in dict.fromkeys(group) if self._slot_of[int(v)] < 0]
                                for group in groups) if not self._cached(new)]
        if not todo:
            return
        vertices = list(dict.fromkeys(v for new in todo for v in new))
        rhs = np.zeros((self._g.shape[0], len(vertices)))
        rhs[vertices, np.arange(len(vertices))] = 1.0
        cols = self._complete_h(rhs)
        inverse, squared = cols[vertices], cols.T @ cols  # K⁻¹, K⁻² among the batch
        index = {v: k for k, v in enumerate(vertices)}
        for new in todo:
            for v in new:
                for w in new:
                    if v <= w:
                        i, j = index[v], index[w]
                        self._entries[v, w] = (float(inverse[i, j]), float(squared[i, j]))
        self._last_batch = dict(zip(vertices, cols.T))

    def _lookup(self, columns: np.ndarray, markers: np.ndarray, slots: np.ndarray, known: np.ndarray,
                which: int) -> np.ndarray:
        """(m, m) block of ``K⁻¹`` (``which`` 0) or ``K⁻²`` (1) among ``markers``: rows of the
        ``known`` markers' columns, the remaining entries from the cache."""
        if known.all():  # the common case: every marker resident
            return columns[markers[:, None], slots]
        rest = np.flatnonzero(~known)
        known = np.flatnonzero(known)
        block = np.empty((markers.size, markers.size))
        block[:, known] = columns[markers[:, None], slots[known]]
        if rest.size:
            block[known[:, None], rest] = block[rest[:, None], known].T
            for i in rest:
                for j in rest:
                    v, w = sorted((int(markers[i]), int(markers[j])))
                    block[i, j] = self._entries[v, w][which]
        return block

    def _inverse_entries(self, markers: np.ndarray, *, squared: bool,
                         trial: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """(m, m) ``K⁻¹`` (and ``K⁻²`` if ``squared``) among ``markers``, from row lookups.

        With ``trial``, up to two non-resident markers (a moved unit) use cached entries;
        otherwise every marker becomes resident.
        """
        slots = self._slot_of[markers]
        resident = slots >= 0
        if resident.sum() < markers.size - (2 if trial else 0):
            slots = self._resident(markers)
            resident[:] = True
        if not resident.all():
            self.prepare([markers[~resident]])
        kinv = self._lookup(self._g, markers, slots, resident, 0)
        if not squared:
            return kinv, None
        with_h = resident.copy()
        with_h[resident] = self._has_h[slots[resident]]
        if not self._cached(markers[~with_h].tolist()):
            self._complete_h()
            with_h = resident
        return kinv, self._lookup(self._h, markers, slots, with_h, 1)

    def _system(self, markers: np.ndarray, kinv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(used components, the (m + c, m + c) system whose solve gives ``λ, s``)."""
        used = np.unique(self.component[markers])
        at_markers = self._anchor_green[markers][:, used]  # K⁻¹[v, anchor] (m, c)
        m, c = markers.size, used.size
        system = np.zeros((m + c, m + c))
        system[:m, :m] = kinv
        system[:m, m:] = self.rho * at_markers
        system[m:, :m] = at_markers.T
        system[m:, m:] = self.rho * self._anchor_green[self.anchors[used]][:, used] - np.eye(c)
        return used, system

    def _coefficients(self, markers: np.ndarray, kinv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(used components, coef (m + c, m)) with ``W = [G, ρ·Ga] @ coef``."""
        used, system = self._system(markers, kinv)
        return used, _identity_solve(system, markers.size)

    def _basis(self, markers: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(slots, used components, coef) of ``W = [G, ρ·Ga] @ coef`` with resident markers."""
        slots = self._resident(markers)
        kinv, _ = self._inverse_entries(markers, squared=False, trial=False)
        used, coef = self._coefficients(markers, kinv)
        return slots, used, coef

    def weights(self, markers: Sequence[int]) -> np.ndarray:
        """(V, M) interpolation weights for the marker vertices ``markers``."""
        markers = np.asarray(markers, dtype=np.intp)
        slots, used, coef = self._basis(markers)
        m = markers.size
        out = self._g[:, slots] @ coef[:m] + self.rho * (self._anchor_green[:, used] @ coef[m:])
        out[markers] = np.eye(m)  # exact at the markers
        return out

    # -- reduced evaluation: everything through (m + c)-sized products, never V×M --------
    def bind(self, data: np.ndarray) -> None:
        """Fix the trajectories ``data`` (V, r) that :meth:`error`, :meth:`fitted` and
        :meth:`expected_trajectories` refer to (r + c triangular solve pairs)."""
        self._data = np.asarray(data, dtype=np.float64)
        self._green_data = self._solve(self._data)  # K⁻¹X (V, r): row v = g_vᵀX
        self._anchor_proj = self._anchor_green.T @ self._data  # (c_all, r)
        self._anchor_dots = self._anchor_green.T @ self._anchor_green  # (c_all, c_all)
        self._anchor_green2 = self._solve(self._anchor_green)  # K⁻²U (V, c): row v = g_vᵀ·Ga
        self._data_norm = float(np.sum(self._data ** 2))
        self._layouts.clear()

    def fitted(self, markers: Sequence[int]) -> np.ndarray:
        """(V, r) reconstruction ``W·X[markers]`` of the bound data."""
        markers = np.asarray(markers, dtype=np.intp)
        slots, used, coef = self._basis(markers)
        m = markers.size
        fit = coef @ self._data[markers]  # (m + c, r)
        out = self._g[:, slots] @ fit[:m] + self.rho * (self._anchor_green[:, used] @ fit[m:])
        out[markers] = self._data[markers]
        return out

    def _reduced(self, markers: np.ndarray, *,
                 trial: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(used components, system, coef, BᵀX, BᵀB) for ``B = [G, ρ·Ga]``: row lookups and
        (m + c)-sized algebra only."""
        kinv, kinv2 = self._inverse_entries(markers, squared=True, trial=trial)
        used, system = self._system(markers, kinv)
        return used, system, _identity_solve(system, markers.size), *self._projections(markers, kinv2, used)

    def _projections(self, markers: np.ndarray, kinv2: np.ndarray,
                     used: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(BᵀX, BᵀB) for ``B = [G, ρ·Ga]`` of ``markers`` and the ``used`` components."""
        m, c = markers.size, used.size
        gram = np.empty((m + c, m + c))
        gram[:m, :m] = kinv2
        cross = self.rho * self._anchor_green2[markers][:, used]  # (m, c)
        gram[:m, m:], gram[m:, :m] = cross, cross.T
        gram[m:, m:] = self.rho ** 2 * self._anchor_dots[np.ix_(used, used)]
        proj = np.concatenate([self._green_data[markers], self.rho * self._anchor_proj[used]])
        return proj, gram

    def error(self, markers: Sequence[int]) -> float:
        """‖X − W·X_H‖² of the bound data for ``markers``, in O((m + c)²·r).

        Up to two markers may be non-resident (a trial move, see :meth:`prepare`)."""
        markers = np.asarray(markers, dtype=np.intp)
        self.evaluations += 1
        _, _, coef, proj, gram = self._reduced(markers, trial=True)
        fitted = coef @ self._data[markers]  # (m + c, r)
        return max(self._data_norm - 2.0 * np.sum(proj * fitted) + np.sum((gram @ fitted) * fitted), 0.0)

    def move_errors(self, markers: Sequence[int], cols: Sequence[int],
                    units: Sequence[Sequence[int]]) -> np.ndarray:
        """:meth:`error` of ``markers`` with the unit at positions ``cols`` moved to each of
        ``units`` (as many vertices each; prepared, see :meth:`prepare`), in one pass.

        The layout without the unit (the base, n = m − k + c unknowns) is solved once; each move
        borders its system by k rows and columns (a k×k Schur complement), and the residual
        ``R' = R₀ + Q·α`` of the base's residual ``R₀`` gives ``‖R'‖²`` from base products:
        O(n²·k + n·k·r) per move instead of an (m + c)-sized solve.
        """
        markers = np.asarray(markers, dtype=np.intp)
        trial_units = np.asarray(units, dtype=np.intp).reshape(len(units), len(cols))
        keep = np.ones(markers.size, dtype=bool)
        keep[list(cols)] = False
        base = markers[keep]
        out = np.empty(len(trial_units))
        if not base.size:
            return self._moved_errors(markers, cols, trial_units, out, np.ones(len(trial_units), dtype=bool))
        used, system, proj, gram = self._base_blocks(markers, keep, base)
        # a move into a component without a base marker changes the anchors: evaluated directly
        in_used = np.zeros(self.anchors.size, dtype=bool)
        in_used[used] = True
        outside = ~in_used[self.component[trial_units]].all(axis=1)
        self._moved_errors(markers, cols, trial_units, out, outside)
        inside = np.flatnonzero(~outside)
        if not inside.size:
            return out
        self.evaluations += inside.size
        moved = trial_units[inside]  # (T, k)
        count, k = moved.shape
        n, m0, r = system.shape[0], base.size, self._data.shape[1]
        slots = self._slot_of[base]
        if not self._has_h[slots].all():  # rows of K⁻² at the base columns are read below
            self._complete_h()
        cross = self._g[moved][:, :, slots]  # K⁻¹[v, base] (T, k, m0)
        cross2 = self._h[moved][:, :, slots]  # K⁻²[v, base]
        anchors = self._anchor_green[moved][:, :, used]  # K⁻¹[v, anchor] (T, k, c)
        column = np.concatenate([cross, anchors], axis=2)  # system rows of the base, column v
        row = np.concatenate([cross, self.rho * anchors], axis=2)  # system row v, base columns
        towards = np.concatenate([cross2, self.rho * self._anchor_green2[moved][:, :, used]], axis=2)
        inner, inner2 = np.empty((count, k, k)), np.empty((count, k, k))
        for t, unit in enumerate(moved):
            if (self._slot_of[unit] < 0).all():  # the common case: entries cached by prepare()
                vertices = unit.tolist()
                for i, v in enumerate(vertices):
                    for j, w in enumerate(vertices):
                        inner[t, i, j], inner2[t, i, j] = self._entries[min(v, w), max(v, w)]
            else:
                inner[t], inner2[t] = self._inverse_entries(unit, squared=True, trial=True)
        rhs = np.zeros((n, count * k + r))
        rhs[:, :count * k] = column.reshape(count * k, n).T
        rhs[:m0, count * k:] = self._data[base]
        solved = np.linalg.solve(system, rhs)
        z = solved[:, :count * k].T.reshape(count, k, n)  # S₀⁻¹·(column v), as rows
        fit = solved[:, count * k:]  # the base's fitted coefficients (n, r)
        gram_fit = gram @ fit
        base_error = self._data_norm - 2.0 * np.sum(proj * fit) + np.sum(gram_fit * fit)
        base_cross = proj - gram_fit  # B₀ᵀR₀ (n, r)
        schur = inner - row @ z.transpose(0, 2, 1)  # (T, k, k)
        alpha = np.linalg.solve(schur, self._data[moved] - row @ fit)  # (T, k, r)
        q_r = z @ base_cross - (self._green_data[moved] - towards @ fit)  # QᵀR₀ (T, k, r)
        zt_towards = z @ towards.transpose(0, 2, 1)
        q_q = z @ gram @ z.transpose(0, 2, 1) - zt_towards - zt_towards.transpose(0, 2, 1) + inner2
        change = 2.0 * np.einsum("tkr,tkr->t", q_r, alpha) + np.einsum("tkr,tkr->t", q_q @ alpha, alpha)
        out[inside] = np.maximum(base_error + change, 0.0)
        return out

    def _base_blocks(self, markers: np.ndarray, keep: np.ndarray,
                     base: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(used components, system, BᵀX, BᵀB) of ``base`` = ``markers[keep]``: rows and columns of
        the layout's kept blocks (the same numbers: every entry is a lookup or an entrywise product)
        when it has them and the base uses the same components, else computed."""
        blocks = self._layouts.get(markers.tobytes())
        if blocks is None or (self.anchors.size > 1  # one component: every base uses it
                              and np.unique(self.component[base]).size != blocks.used.size):
            return self._computed_base(base)
        index = np.concatenate([np.flatnonzero(keep), np.arange(markers.size, markers.size + blocks.used.size)])
        return (blocks.used, blocks.system.take(index, 0).take(index, 1), blocks.proj.take(index, 0),
                blocks.gram.take(index, 0).take(index, 1))

    def _computed_base(self, base: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`_base_blocks` from the entries of ``K⁻¹`` and ``K⁻²`` among ``base``."""
        kinv0, kinv2_0 = self._inverse_entries(base, squared=True, trial=False)
        used, system = self._system(base, kinv0)
        return used, system, *self._projections(base, kinv2_0, used)

    def _moved_errors(self, markers: np.ndarray, cols: Sequence[int], units: np.ndarray, out: np.ndarray,
                      which: np.ndarray) -> np.ndarray:
        """:meth:`error` of each move flagged in ``which``, written into ``out``."""
        for t in np.flatnonzero(which):
            trial = markers.copy()
            trial[list(cols)] = units[t]
            out[t] = self.error(trial)
        return out

    def expected_trajectories(self, markers: Sequence[int], cols: Sequence[int]) -> np.ndarray:
        """(len(cols), r) Le et al.'s expected trajectories ``H̄j = Wjᵀ·Rj / (Wjᵀ·Wj)`` of the
        markers at positions ``cols``, where ``Rj`` leaves out the contribution of all ``cols``.

        ``WᵀX``, ``WᵀW`` and the layout's system and projections are kept per layout until
        :meth:`forget` or :meth:`bind`: a sweep asks for every unit of the same layout until one
        moves, and :meth:`move_errors` reads each unit's base from them."""
        markers = np.asarray(markers, dtype=np.intp)
        blocks = self._layouts.get(markers.tobytes())
        if blocks is None:
            used, system, coef, proj, gram = self._reduced(markers, trial=False)
            blocks = self._layouts[markers.tobytes()] = _LayoutBlocks(
                used, system, proj, gram, coef.T @ proj, coef.T @ gram @ coef)
        w_x, w_w = blocks.w_x, blocks.w_w
        others = np.ones(markers.size, dtype=bool)
        others[list(cols)] = False
        others = np.flatnonzero(others)
        traj = self._data[markers[others]]
        return np.stack([(w_x[j] - w_w[j, others] @ traj) / w_w[j, j] for j in cols])


@dataclass(frozen=True, eq=False)
class _LayoutBlocks:
    """What :class:`ThinShellWeights` keeps of one layout (n = m + c unknowns): the used
    components, the (n, n) system, ``BᵀX`` (n, r), ``BᵀB`` (n, n), ``WᵀX`` (m, r), ``WᵀW`` (m, m)."""

    used: np.ndarray
    system: np.ndarray
    proj: np.ndarray
    gram: np.ndarray
    w_x: np.ndarray
    w_w: np.ndarray


def _identity_solve(system: np.ndarray, m: int) -> np.ndarray:
    """(n, m) ``system⁻¹`` applied to the first ``m`` unit vectors (the coefficients of ``W``)."""
    rhs = np.zeros((system.shape[0], m))
    rhs[:m] = np.eye(m)
    return np.linalg.solve(system, rhs)


@dataclass(frozen=True)
class ThinShellResult:
    """Best layout (sorted vertex indices), its training RMSE (mm) and optimizer statistics
    (``solves``: triangular solve pairs; ``evaluations``: layouts whose error was computed)."""

    layout: np.ndarray
    rmse_mm: float
    iterations: list[int]
    moves: int
    solves: int
    factor_seconds: float
    seconds: float
    evaluations: int = 0


def trajectory_matrix(displacements: np.ndarray) -> np.ndarray:
    """(V, 3F) one row per vertex: its displacement trajectory (x, y, z per frame)."""
    disp = np.asarray(displacements, dtype=np.float64)
    return disp.transpose(1, 0, 2).reshape(disp.shape[1], -1)


def mirrored_frames(displacements: np.ndarray, mirror: np.ndarray, *, axis: int = 0) -> np.ndarray:
    """The data plus its mirror image (frames doubled): vertex v takes its partner's motion, flipped."""
    flipped = displacements[:, mirror].copy()
    flipped[..., axis] *= -1.0
    return np.concatenate([displacements, flipped], axis=0)


def border_vertices(faces: np.ndarray, count: int, positions: np.ndarray) -> np.ndarray:
    """``count`` vertices spread along the mesh boundary (farthest-point along the border), sorted."""
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    border = np.unique(uniq[counts == 1])
    if count > border.size:
        raise OptionError(f"the mesh border has {border.size} vertices, {count} requested")
    pts = positions[border]
    chosen = [int(np.argmax(np.linalg.norm(pts - pts.mean(axis=0), axis=1)))]
    dist = np.linalg.norm(pts - pts[chosen[0]], axis=1)
    while len(chosen) < count:
        chosen.append(int(np.argmax(dist)))
        dist = np.minimum(dist, np.linalg.norm(pts - pts[chosen[-1]], axis=1))
    return np.sort(border[chosen])


class _Layout:
    """Marker set as units (a single vertex, or a mirrored pair) that move together."""

    def __init__(self, units: list[tuple[int, ...]], movable: list[bool]) -> None:
        self.units = units
        self.movable = movable

    @property
    def markers(self) -> list[int]:
        return [v for unit in self.units for v in unit]

    def columns(self, unit: int) -> list[int]:
        """Positions of ``unit``'s vertices in :attr:`markers`."""
        start = sum(len(self.units[k]) for k in range(unit))
        return list(range(start, start + len(self.units[unit])))


def compress_trajectories(trajectories: np.ndarray, *, max_rank: int = 96,
                          energy: float = 0.99999) -> np.ndarray:
    """(V, r) coordinates of the trajectories in their principal subspace (r ≤ ``max_rank``).

    Distances between trajectories and reconstruction errors ``‖X − W·X_H‖`` are preserved
    exactly when the data's rank is ≤ r (and up to the discarded ``1 − energy`` otherwise), so the
    optimizer works on V×r instead of V×3F numbers.
    """
    x = np.asarray(trajectories, dtype=np.float64)
    if x.shape[1] <= max_rank:
        return x
    # X = U·S·Vᵀ: the coordinates X·V = U·S, from the smaller of the two Gram matrices
    small_side = x.shape[0] < x.shape[1]
    gram = x @ x.T if small_side else x.T @ x
    total = float(np.trace(gram))  # all of the energy, without all of the eigenvalues
    top = min(max_rank, gram.shape[0])
    vals, vecs = sla.eigh(gram, subset_by_index=[gram.shape[0] - top, gram.shape[0] - 1])
    vals, vecs = np.maximum(vals[::-1], 0.0), vecs[:, ::-1]
    cumulative = np.cumsum(vals)
    rank = int(np.searchsorted(cumulative, energy * total) + 1) if total > 0 else 1
    rank = min(rank, top)
    if small_side:
        return vecs[:, :rank] * np.sqrt(vals[:rank])
    return x @ vecs[:, :rank]


def mesh_neighbours(faces: np.ndarray, n_vertices: int) -> sp.csr_matrix:
    """(V, V) vertex adjacency (1-ring) of a triangle mesh."""
    f = np.asarray(faces, dtype=np.intp)
    rows = np.concatenate([f[:, 0], f[:, 1], f[:, 2], f[:, 1], f[:, 2], f[:, 0]])
    cols = np.concatenate([f[:, 1], f[:, 2], f[:, 0], f[:, 0], f[:, 1], f[:, 2]])
    adj = sp.csr_matrix((np.ones(rows.size), (rows, cols)), shape=(n_vertices, n_vertices))
    adj.data[:] = 1.0
    return adj


@single_threaded
def optimize_thin_shell(trajectories: np.ndarray, solver: ThinShellWeights, count: int, *,
                        candidates: np.ndarray | None = None, fixed: Sequence[int] = (),
                        mirror: np.ndarray | None = None, neighbours: sp.spmatrix | None = None,
                        iterations: int = 10, restarts: int = 10,
                        initial: Sequence[int] | None = None, verify: bool = True,
                        candidates_per_move: int = 3, seed: int = 0,
                        frames: int | None = None) -> ThinShellResult:
    """Block coordinate descent of Le et al. over ``restarts`` starts.

    Parameters
    ----------
    trajectories : (V, 3F) float, mm
        Per-vertex displacement trajectories (:func:`trajectory_matrix`), or their
        :func:`compress_trajectories` coordinates with ``frames`` = F (the RMSE is per frame).
    solver : ThinShellWeights
        Factorized thin-shell operator of the mesh.
    count : int
        Markers in the layout (``fixed`` ones included).
    candidates : (K,) int, optional
        Vertices a marker may occupy (default all).
    fixed : vertex indices
        Markers that never move (boundary constraint; a smaller layout kept for multiresolution).
    mirror : (V,) int, optional
        Symmetry constraint: markers come in mirrored pairs ``(v, mirror[v])``, or sit on the
        midline (``mirror[v] == v``). Pass mirrored data (:func:`mirrored_frames`) with it.
    neighbours : (V, V) sparse, optional
        Mesh adjacency; with ``verify`` the 1-ring of a marker is tried too.
    initial : vertex indices, optional
        Start of the first restart (default: markers inserted one by one where the fit is worst);
        later restarts are random.
    verify : bool
        Our extension of the paper's step. ``False``: Le et al. as written — each marker moves to
        the vertex whose trajectory is closest to its expected trajectory, until no marker moves.
        ``True`` (default): the ``candidates_per_move`` closest vertices and the marker's 1-ring are
        scored by the actual reconstruction error and the best is kept only if the error drops
        (monotone descent), and when a sweep moves nothing, one marker may jump to a
        badly-fitted vertex. As written, the step is not stable: even next to the optimum the
        other markers' expected trajectories are biased by the misplaced one and they drift.

    BLAS runs single-threaded inside: the work is many small dense products, for which BLAS
    threads only add synchronization (on 2 busy cores they tripled the CPU time).
    """
    started = time.perf_counter()
    x = compress_trajectories(trajectories)
    n = x.shape[0]
    allowed = np.zeros(n, dtype=bool)
    allowed[np.arange(n) if candidates is None else np.asarray(candidates, dtype=np.intp)] = True
    fixed = [int(v) for v in fixed]
    if not 1 <= count <= int(allowed.sum()) + len(fixed) or len(fixed) > count:
        raise OptionError(f"layout size must be between {max(len(fixed), 1)} and {int(allowed.sum())}, "
                          f"got {count}")
    sq_norm = np.einsum("ij,ij->i", x, x)
    solver.bind(x)
    ring = None if neighbours is None else sp.csr_matrix(neighbours)
    rng = np.random.default_rng(seed)
    best: tuple[float, list[int]] | None = None
    iteration_counts: list[int] = []
    moves = 0
    for restart in range(restarts):
        if restart == 0 and initial is None:
            initial = _insertion_start(x, solver, count, fixed, allowed, mirror)
        layout = _start(count, fixed, allowed, mirror, rng, initial if restart == 0 else None)
        current = solver.error(layout.markers)
        unsettled = [True] * len(layout.units)
        sweeps = 0
        for _ in range(iterations):
            sweeps += 1
            moved = False
            for u in rng.permutation(len(layout.units)):
                if not layout.movable[u]:
                    continue
                targets = _closest_units(x, sq_norm, solver, layout, int(u), allowed, mirror,
                                         candidates_per_move if verify else 1)
                if not verify:
                    if targets:
                        layout.units[u] = targets[0]
                        moved, moves = True, moves + 1
                    continue
                # 1-ring places are tried only while the marker has not settled (it moved in
                # this start's previous sweep, or this is the first sweep)
                if unsettled[u]:
                    targets += _ring_units(ring, layout, int(u), allowed, mirror)
                solver.prepare(targets)  # one multi-RHS solve for the new places
                old = layout.units[u]
                best_unit = old
                trials = list(dict.fromkeys(targets))
                errors = solver.move_errors(layout.markers, layout.columns(int(u)), trials) if trials else []
                for unit, err in zip(trials, errors):
                    if err < current * (1.0 - 1e-12):
                        current, best_unit = err, unit
                layout.units[u] = best_unit
                unsettled[u] = best_unit != old
                if best_unit != old:
                    moved, moves = True, moves + 1
            if verify and not moved:
                jumped = _jump(x, solver, layout, allowed, mirror, current)
                if jumped is not None:
                    current, moved, moves = jumped, True, moves + 1
                    unsettled = [True] * len(layout.units)
            solver.forget(layout.markers)
            if not moved:
                break
        iteration_counts.append(sweeps)
        markers = layout.markers
        err = float(np.sum((x - solver.fitted(markers)) ** 2))  # exact, once per start
        if best is None or err < best[0]:
            best = (err, sorted(markers))
    assert best is not None
    frame_count = np.asarray(trajectories).shape[1] / 3 if frames is None else frames
    rmse = float(np.sqrt(best[0] / (n * frame_count)))
    return ThinShellResult(np.array(best[1], dtype=np.intp), rmse, iteration_counts, moves,
                           solver.solves, 0.0, time.perf_counter() - started, solver.evaluations)


def _ring_units(ring: sp.csr_matrix | None, layout: _Layout, unit: int, allowed: np.ndarray,
                mirror: np.ndarray | None) -> list[tuple[int, ...]]:
    """The unit moved to each free 1-ring neighbour of its first vertex."""
    if ring is None:
        return []
    members = layout.units[unit]
    v = members[0]
    taken = set(layout.markers) - set(members)
    out: list[tuple[int, ...]] = []
    for w in ring.indices[ring.indptr[v]:ring.indptr[v + 1]]:
        w = int(w)
        if not allowed[w] or w in taken:
            continue
        if len(members) == 1:
            if mirror is None or mirror[w] == w:
                out.append((w,))
        elif mirror[w] != w and int(mirror[w]) not in taken and allowed[mirror[w]]:
            out.append((w, int(mirror[w])))
    return out


def _jump(x: np.ndarray, solver: ThinShellWeights, layout: _Layout, allowed: np.ndarray,
          mirror: np.ndarray | None, current: float, targets: int = 4) -> float | None:
    """Relocate one unit to one of the ``targets`` worst-fitted free vertices if that lowers the
    error; returns the new error (None: no improving jump)."""
    markers = layout.markers
    residual = x - solver.fitted(markers)
    per_vertex = np.einsum("ij,ij->i", residual, residual)
    free = allowed.copy()
    free[markers] = False
    if mirror is not None:
        free[mirror[markers]] = False
    best_err, best_move = current * (1.0 - 1e-12), None
    on_midline = None if mirror is None else mirror == np.arange(len(mirror))
    moves: list[tuple[int, tuple[int, ...]]] = []
    for u, unit in enumerate(layout.units):
        if not layout.movable[u]:
            continue
        mask = free.copy()
        if on_midline is not None:
            mask &= on_midline if len(unit) == 1 else ~on_midline
        places = np.flatnonzero(mask)
        for v in places[np.argsort(-per_vertex[places], kind="stable")[:targets]]:
            moves.append((u, (int(v),) if len(unit) == 1 else (int(v), int(mirror[v]))))
    solver.prepare([new_unit for _, new_unit in moves])  # one multi-RHS solve
    for u in dict.fromkeys(u for u, _ in moves):
        units = [new_unit for w, new_unit in moves if w == u]
        for new_unit, err in zip(units, solver.move_errors(markers, layout.columns(u), units)):
            if err < best_err:
                best_err, best_move = err, (u, new_unit)
    if best_move is None:
        return None
    layout.units[best_move[0]] = best_move[1]
    return best_err


def _insertion_start(x: np.ndarray, solver: ThinShellWeights, count: int, fixed: list[int],
                     allowed: np.ndarray, mirror: np.ndarray | None) -> list[int]:
    """Markers added one by one at the worst-reconstructed allowed vertex (largest motion first)."""
    chosen = list(fixed)
    free = allowed.copy()
    free[chosen] = False
    while len(chosen) < count and free.any():
        residual = x - solver.fitted(chosen) if chosen else x
        per_vertex = np.einsum("ij,ij->i", residual, residual)
        v = int(np.flatnonzero(free)[np.argmax(per_vertex[free])])
        new = [v] if mirror is None or count - len(chosen) < 2 else list(dict.fromkeys([v, int(mirror[v])]))
        chosen += new
        free[new] = False
    return chosen


def _closest_units(x: np.ndarray, sq_norm: np.ndarray, solver: ThinShellWeights, layout: _Layout,
                   unit: int, allowed: np.ndarray, mirror: np.ndarray | None,
                   how_many: int) -> list[tuple[int, ...]]:
    """The unit's ``how_many`` best new places (trajectories closest to the expected ones) that
    beat staying put, best first (empty if staying is best)."""
    markers = layout.markers
    members = list(layout.units[unit])
    start = sum(len(layout.units[k]) for k in range(unit))
    cols = list(range(start, start + len(members)))
    others = [k for k in range(len(markers)) if k not in cols]
    expected_all = solver.expected_trajectories(markers, cols)
    cost = np.zeros(x.shape[0])
    for member, expected in enumerate(expected_all):
        dist = sq_norm - 2.0 * (x @ expected)
        cost += dist if member == 0 else dist[mirror]  # the pair's second vertex is mirror[v]
    free = allowed.copy()
    taken = [markers[k] for k in others]
    free[taken] = False
    if mirror is not None:
        free[mirror[taken]] = False
        on_midline = mirror == np.arange(x.shape[0])
        free &= on_midline if len(members) == 1 else ~on_midline
    free[members[0]] = False
    stay = cost[members[0]] - 1e-12 * abs(cost[members[0]])
    places = np.flatnonzero(free & (cost < stay))
    places = places[np.argsort(cost[places], kind="stable")[:how_many]]
    return [(int(v),) if len(members) == 1 else (int(v), int(mirror[v])) for v in places]


def _start(count: int, fixed: list[int], allowed: np.ndarray, mirror: np.ndarray | None,
           rng: np.random.Generator, initial: Sequence[int] | None) -> _Layout:
    units: list[tuple[int, ...]] = [(v,) for v in fixed]
    movable = [False] * len(units)
    used = set(fixed)
    pool = [int(v) for v in (initial if initial is not None else rng.permutation(np.flatnonzero(allowed)))]
    if initial is not None:  # top up a short initial layout with random vertices
        pool += [int(v) for v in rng.permutation(np.flatnonzero(allowed))]
    remaining = count - len(fixed)
    for v in pool:
        if remaining <= 0:
            break
        if v in used or not allowed[v]:
            continue
        if mirror is None or mirror[v] == v:
            unit: tuple[int, ...] = (v,)
        elif remaining >= 2 and int(mirror[v]) not in used and allowed[mirror[v]]:
            unit = (v, int(mirror[v]))
        else:
            continue
        units.append(unit)
        movable.append(True)
        used.update(unit)
        remaining -= len(unit)
    if remaining:
        raise OptionError("cannot place that many markers under the symmetry constraint")
    return _Layout(units, movable)


def thin_shell_layout(problem: LayoutProblem, count: int, *, ks: float = 1.0, kb: float = 10.0,
                      iterations: int = 10, restarts: int = 10, fixed: Sequence[int] = (),
                      border_markers: int = 0, symmetric: bool = False,
                      initial: Sequence[int] | None = None, verify: bool = True,
                      seed: int = 0) -> ThinShellResult:
    """Le et al.'s optimizer on a layout problem (mesh = ``problem.surface_faces()``).

    ``border_markers`` fixed markers are spread along the mesh border (boundary constraint);
    ``fixed`` keeps given points (multiresolution); ``symmetric`` needs ``problem.mirror`` and uses
    mirrored data with paired markers. Gap-free frames only (:meth:`LayoutProblem.complete_frames`).
    """
    faces = problem.surface_faces()
    t0 = time.perf_counter()
    # one factorization per problem: compare runs the optimizer at every count, and the hybrid too
    solver = problem.cached(("thin-shell-solver", ks, kb), lambda: ThinShellWeights(
        thin_shell_operator(problem.neutral, faces, ks=ks, kb=kb))).fresh()
    factor_seconds = time.perf_counter() - t0
    mirror = None
    if symmetric:
        if problem.mirror is None:
            raise OptionError("symmetric layouts need the mirror partner of every point")
        mirror = problem.mirror

    def training_data() -> tuple[np.ndarray, int]:
        disp = problem.complete_frames()
        disp = disp if mirror is None else mirrored_frames(disp, mirror)
        return compress_trajectories(trajectory_matrix(disp)), disp.shape[0]

    # compressed once per problem: compare runs the optimizer at every count, and the hybrid too
    data, frames = problem.cached(("thin-shell-data", symmetric), training_data)
    pinned = list(dict.fromkeys([int(v) for v in fixed]
                                + ([int(v) for v in border_vertices(faces, border_markers, problem.neutral)]
                                   if border_markers else [])))
    result = optimize_thin_shell(data, solver, count, frames=frames,
                                 candidates=problem.candidate_points(), fixed=pinned, mirror=mirror,
                                 neighbours=mesh_neighbours(faces, problem.n_points), iterations=iterations,
                                 restarts=restarts, initial=initial, verify=verify, seed=seed)
    return ThinShellResult(result.layout, result.rmse_mm, result.iterations, result.moves,
                           result.solves, factor_seconds, result.seconds + factor_seconds,
                           result.evaluations)
