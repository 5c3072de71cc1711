"""Fill per-vertex values where they are unknown, smoothly, keeping known values exactly
(DESIGN §5 step 6, the paper's "Occlusion Handling").

Two methods:

- ``harmonic``: the Laplace equation with the assigned values as Dirichlet data, solved
  on the unknown vertices only with a sparse Cholesky factorisation (CHOLMOD through
  cvxopt, simplicial LDL^T, eliminating in a minimum-degree order of the whole mesh
  computed once per `FillSystem`; SuperLU with pivoting where the factorisation meets a
  zero pivot).
  The operator is potpourri3d's cotangent Laplacian (`laplacian_matrix`), so a linear
  field on a flat patch is reproduced exactly for any triangulation. The intrinsic
  Delaunay Laplacian (robust_laplacian) was measured against it on the built-in garment
  (benchmarks/fill_laplacian.py): identical on its rest shape, slightly less accurate on a
  folded reference shape, so it serves only as the fallback for degenerate triangles.
- ``fmm``: the paper's recipe. Geodesic distance from the assigned set by the heat method
  (potpourri3d's `MeshHeatMethodDistanceSolver`, not fast marching proper), extension of
  the values along it (each unassigned vertex, in increasing distance, takes the average
  of its already-known *upwind* neighbours, weighted by how well the edge follows the
  distance gradient: values travel along the characteristics as in level-set velocity
  extension), then a few Jacobi averaging passes that keep the assigned values fixed.

Seams: with ``groups`` (e.g. `mvtex.data.mesh.weld_groups`), vertices of one group are solved
as one vertex (the copies of a seam vertex share one position and, where the UV charts
agree, one displacement); an assigned vertex keeps its own value bit for bit, an
unassigned one receives its group's value. Connected parts with no assigned vertex get 0.
"""

from __future__ import annotations

import threading

import numpy as np
import scipy.sparse as sp
import scipy.sparse.csgraph as csgraph
from scipy.sparse.linalg import splu, spsolve

from mvtex.data.dataset import validate_mesh
from mvtex.data.mesh import adjacency, edges
from mvtex.util.checks import as_array, check_shape
from mvtex.util.errors import InputError, OptionError

METHODS = ("harmonic", "fmm")


LAPLACIANS = ("cotan", "intrinsic")


HARMONIC_LAPLACIAN = "cotan"  # the harmonic fill's Laplacian (measured: see benchmarks/fill_laplacian.py)


def laplacian_matrix(positions: np.ndarray, faces: np.ndarray, kind: str = "cotan") -> sp.csr_matrix:
    """Symmetric positive semi-definite (n,n) Laplacian L = D - W of a triangle mesh, from a
    library:

    - "cotan": the cotangent Laplacian, W_ij = (cot α + cot β) / 2
      (`potpourri3d.cotan_laplacian`). Exact for linear fields on any flat triangulation;
      an edge opposite two obtuse angles gets a negative weight.
    - "intrinsic": the cotangent Laplacian of the intrinsic Delaunay triangulation
      (`robust_laplacian.mesh_laplacian`, Sharp & Crane 2020): non-negative weights by
      construction (a maximum principle on every mesh, folded or not), and equal to
      "cotan" where the mesh is already Delaunay.

    "cotan" falls back to "intrinsic" on a mesh with zero-area triangles.

    Args:
        positions: (n,3) float positions. faces: (m,3) int (unreferenced vertices are isolated).
        kind: one of `LAPLACIANS`.
    """
    p = np.ascontiguousarray(positions, dtype=np.float64)
    f = np.ascontiguousarray(faces, dtype=np.int64)
    if kind == "cotan":
        import potpourri3d as pp3d  # noqa: PLC0415 (loaded on use)

        with np.errstate(divide="ignore", invalid="ignore"):
            L = pp3d.cotan_laplacian(p, f)
        if not np.all(np.isfinite(L.data)):
            # Zero-area triangles have no cotangents; the intrinsic operator is defined on
            # every mesh.
            return laplacian_matrix(p, f, "intrinsic")
    elif kind == "intrinsic":
        import robust_laplacian  # noqa: PLC0415 (loaded on use)

        L = robust_laplacian.mesh_laplacian(p, f)[0]
    else:
        raise ValueError(f"unknown Laplacian {kind!r} (use {' or '.join(LAPLACIANS)})")
    L = sp.csr_matrix(L, dtype=np.float64)
    L.sum_duplicates()
    # Edges opposite two right angles (a regular grid's diagonals) weigh exactly 0: leaving
    # them out keeps the elimination order and the factorisation sparse.
    L.eliminate_zeros()
    return L


def _welded(faces: np.ndarray, positions: np.ndarray, groups: np.ndarray | None):
    """Compact welded mesh: (faces_w, positions_w, index (n,) vertex -> welded vertex)."""
    n = len(positions)
    if groups is None:
        return np.asarray(faces, dtype=np.int64), np.asarray(positions, dtype=np.float64), np.arange(n)
    groups = np.asarray(groups, dtype=np.int64)
    if groups.shape != (n,):
        raise ValueError(f"groups must have shape ({n},), got {groups.shape}")
    reps, index = np.unique(groups, return_inverse=True)
    index = index.reshape(-1)
    faces_w = index[np.asarray(faces, dtype=np.int64)]
    # Seam copies share one position; take the first member's.
    first = np.full(len(reps), -1)
    first[index[::-1]] = np.arange(n)[::-1]
    return faces_w, np.asarray(positions, dtype=np.float64)[first], index


def _group_dirichlet(values: np.ndarray, assigned: np.ndarray, index: np.ndarray, ng: int):
    """Per welded vertex: assigned flag and the mean of its assigned members' values."""
    a_idx = np.flatnonzero(assigned)
    count = np.bincount(index[a_idx], minlength=ng).astype(np.float64)
    rows = values[a_idx].astype(np.float64)
    # bincount adds in input order, as a loop over the assigned vertices would.
    acc = np.stack([np.bincount(index[a_idx], rows[:, c], minlength=ng) for c in range(values.shape[1])], axis=1)
    acc = acc.astype(np.float64, copy=False)  # bincount of no vertex at all is integer
    known = count > 0
    np.divide(acc, count[:, None], out=acc, where=known[:, None])
    return known, acc


def _zero_unreachable(adj: sp.csr_matrix, known: np.ndarray, vals: np.ndarray) -> np.ndarray:
    """Mark vertices of components with no known vertex as known with value 0."""
    ncomp, label = csgraph.connected_components(adj, directed=False)
    has = np.zeros(ncomp, bool)
    has[label[known]] = True
    lost = ~has[label]
    vals[lost] = 0.0
    return known | lost


class FillSystem:
    """The pose-independent part of a harmonic fill, built once per mesh: welding and the
    Laplacian on `positions` (e.g. a rest shape). Pass it to `fill(system=...)` to fill
    many value sets on the same mesh without rebuilding the Laplacian.

    Args:
        faces: (m,3) int. positions: (n,3) float. groups: optional (n,) seam groups.
        laplacian: `laplacian_matrix` kind (default `HARMONIC_LAPLACIAN`).
    """

    def __init__(self, faces: np.ndarray, positions: np.ndarray, groups: np.ndarray | None = None, *,
                 laplacian: str | None = None):
        self.num_vertices = len(positions)
        faces_w, pos_w, self.index = _welded(faces, positions, groups)
        self.num_welded = len(pos_w)
        self.kind = HARMONIC_LAPLACIAN if laplacian is None else laplacian
        self.laplacian = laplacian_matrix(pos_w, faces_w, self.kind)
        self.label = csgraph.connected_components(self.laplacian, directed=False)[1]
        self._lower = sp.tril(self.laplacian, format="csc")
        self._lower.sort_indices()
        self._rank: np.ndarray | None = None
        self._order: np.ndarray | None = None

    @property
    def order(self) -> np.ndarray:
        """(num_welded,) int64 welded vertices in elimination order (`rank` inverted)."""
        if self._order is None:
            self._order = np.argsort(self.rank, kind="stable")
        return self._order

    @property
    def rank(self) -> np.ndarray:
        """(num_welded,) int64 position of each welded vertex in a fill-reducing elimination
        order of the whole Laplacian (minimum degree on its graph), computed on first use.

        Every Dirichlet problem on this mesh eliminates its unknowns in this order: the
        restriction of a good order to a subgraph stays good, and the per-solve ordering
        (a third of a factorisation's time on a ~6k unknown system) is skipped.
        """
        if self._rank is None:

            L = self.laplacian
            # L is singular (constants); a tiny diagonal shift makes it factorisable. Only
            # the column order of this factorisation is kept.
            shift = 1e-6 * max(float(np.abs(L.diagonal()).max(initial=0.0)), 1e-300)
            lu = splu((L + shift * sp.identity(L.shape[0], format="csr")).tocsc(), permc_spec="MMD_AT_PLUS_A",
                      diag_pivot_thresh=0.0, options={"SymmetricMode": True})
            # SuperLU factors A[:, perm_c]-style: column j of A goes to position perm_c[j].
            self._rank = np.asarray(lu.perm_c, dtype=np.int64)
        return self._rank

    def lower_submatrix(self, vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The lower triangle of L[vertices][:, vertices] for increasing `vertices` ((k,)
        distinct welded indices), as coordinate triplets (values, rows, columns)."""
        vertices = np.asarray(vertices, dtype=np.int64)
        if np.any(np.diff(vertices) <= 0):
            raise ValueError("lower_submatrix needs increasing vertex indices")
        local = np.full(self.num_welded, -1, np.int64)
        local[vertices] = np.arange(len(vertices))
        selected = self._lower[:, vertices]
        rows = local[selected.indices]
        keep = rows >= 0  # rows of other vertices are dropped
        cols = np.repeat(np.arange(len(vertices), dtype=np.int64), np.diff(selected.indptr))
        return selected.data[keep], rows[keep], cols[keep]


def fill(faces: np.ndarray, positions: np.ndarray, values: np.ndarray, assigned: np.ndarray,
         method: str = "harmonic", groups: np.ndarray | None = None, *, smoothing_passes: int = 4,
         system: FillSystem | None = None) -> np.ndarray:
    """Extend per-vertex values from assigned vertices to all vertices.

    Args:
        faces: (m,3) int triangles.
        positions: (n,3) float vertex positions (weights and distances are measured on them).
        values: (n,C) float values; rows where `assigned` is False are ignored.
        assigned: (n,) bool.
        method: "harmonic" (cotangent Laplace, Dirichlet at assigned) or "fmm" (heat-method
            distance, upwind extension, then `smoothing_passes` Jacobi passes).
        groups: optional (n,) int group id per vertex (seam copies share one); vertices of a
            group are solved as one.
        smoothing_passes: Jacobi passes after the fmm extension.
        system: a `FillSystem` of this mesh (harmonic only): its Laplacian (measured on the
            positions it was built from) is used instead of one from `positions`.

    Returns:
        (n,C) array of values' dtype (float64 if values is integer); assigned rows are the
        input rows unchanged, bit for bit. Parts of the mesh with no assigned vertex get 0.
    """

    if not isinstance(method, str) or method not in METHODS:
        raise OptionError("method", f"must be one of {', '.join(METHODS)}, got {method!r:.60}")
    if system is None or not isinstance(values, np.ndarray) or values.ndim != 1:  # checked once, not per column
        positions = as_array(positions, "positions")
        sizes = check_shape(positions, "positions", ("n", 3))
        faces = as_array(faces, "faces", None)
        try:
            validate_mesh(faces, np.zeros((len(positions), 2)), None)
        except InputError as err:
            raise OptionError(None, f"faces: {err.problem}") from None
        if not np.all(np.isfinite(positions)):
            raise OptionError("positions", "has NaN or infinite values")
        values = as_array(values, "values", None)
        if values.ndim not in (1, 2) or values.dtype.kind not in "biuf":
            raise OptionError("values", f"must be numbers with shape (n,) or (n,C), got {values.shape} {values.dtype}")
        check_shape(values[:, None] if values.ndim == 1 else values, "values", ("n", "C"), sizes)
        if not np.all(np.isfinite(values[np.asarray(assigned, dtype=bool)] if np.shape(assigned) == (len(values),)
                                  else values)):
            raise OptionError("values", "has NaN or infinite values where assigned")
        assigned = as_array(assigned, "assigned", None)
        if assigned.dtype != np.bool_:
            raise OptionError("assigned", f"must be bool, got {assigned.dtype}")
        check_shape(assigned, "assigned", ("n",), sizes)
        if groups is not None:
            groups = as_array(groups, "groups", None)
            check_shape(groups, "groups", ("n",), sizes)
            if groups.dtype.kind not in "iu" or (len(groups) and groups.min() < 0):
                raise OptionError("groups", "must be non-negative integers, one per vertex")
    values = np.asarray(values)
    if values.ndim == 1:
        return fill(faces, positions, values[:, None], assigned, method, groups,
                    smoothing_passes=smoothing_passes, system=system)[:, 0]
    assigned = np.asarray(assigned, dtype=bool)
    n = len(positions)
    if values.shape[0] != n or assigned.shape != (n,):
        raise ValueError(f"values {values.shape} and assigned {assigned.shape} must have {n} rows")
    out_dtype = values.dtype if np.issubdtype(values.dtype, np.floating) else np.float64
    out = np.array(values, dtype=out_dtype, copy=True)
    if assigned.all():
        return out
    if method == "harmonic":
        if system is None:
            system = FillSystem(faces, positions, groups)
        elif system.num_vertices != n:
            raise ValueError(f"fill system built for {system.num_vertices} vertices, values have {n}")
        index = system.index
        known, vals = _group_dirichlet(values, assigned, index, system.num_welded)
        solved = _harmonic(system, known, vals)
    else:
        faces_w, pos_w, index = _welded(faces, positions, groups)
        known, vals = _group_dirichlet(values, assigned, index, len(pos_w))
        solved = _fmm(faces_w, pos_w, known, vals, smoothing_passes)
    free = ~assigned
    out[free] = solved[index[free]].astype(out_dtype)
    return out


def _harmonic(system: FillSystem, known: np.ndarray, vals: np.ndarray) -> np.ndarray:
    L = system.laplacian
    # Components with no known vertex are set to 0 (and become known).
    has = np.zeros(system.label.max() + 1, bool)
    has[system.label[known]] = True
    lost = ~has[system.label]
    vals[lost] = 0.0
    known = known | lost
    if known.all():
        return vals
    u = np.flatnonzero(~known)
    # The unknowns' elimination order (see `FillSystem.rank`) as positions in u: position
    # of each unknown among the unknowns, taken in the system's order.
    position = np.cumsum(~known) - 1
    order = system.order
    elimination = position[order[~known[order]]]
    # Only known values enter the right-hand side: the unknown entries are 0 here, and a
    # product with 0 adds nothing to a row sum (each row is summed in the same order as in
    # L[u] @ vals, so taking rows u of the whole product gives the same bits, faster).
    vals[u] = 0.0
    rhs = -(L @ vals)[u]
    # Every unknown's component touches a known vertex, so L_uu is nonsingular and
    # symmetric positive definite (a principal submatrix of a connected Laplacian).
    vals[u] = solve_spd(system.lower_submatrix(u), len(u), rhs, order=elimination)
    return vals


_CHOLMOD_LOCK = threading.Lock()


def solve_spd(lower: tuple[np.ndarray, np.ndarray, np.ndarray], k: int, rhs: np.ndarray,
              order: np.ndarray | None = None) -> np.ndarray:
    """Solve A x = rhs for a sparse symmetric positive definite A (k,k) given by its lower
    triangle as triplets (values, rows, columns); rhs (k,) or (k,C) float.

    CHOLMOD (through cvxopt) factors A = L D L^T, simplicial (no BLAS, so the same bits
    whatever the thread count), eliminating in `order` ((k,) permutation of range(k)) or,
    if None, in CHOLMOD's approximate-minimum-degree order. A block
    that meets a zero pivot (degenerate triangles can make it singular in floating point)
    is solved by SuperLU with partial pivoting instead. cvxopt's `cholmod.options` are set for the call
    and restored, under a lock (cvxopt keeps them in one module-level dict).
    """
    from cvxopt import cholmod, matrix, spmatrix  # noqa: PLC0415 (loaded on use)

    values, rows, cols = lower
    b = np.array(rhs, dtype=np.float64, order="F", copy=True)
    if b.ndim == 1:
        return solve_spd(lower, k, b[:, None], order)[:, 0]
    A = spmatrix(np.asarray(values, np.float64), np.asarray(rows, np.int64), np.asarray(cols, np.int64), (k, k))
    B = matrix(b)
    with _CHOLMOD_LOCK:
        saved = dict(cholmod.options)
        cholmod.options.clear()
        cholmod.options["supernodal"] = 0
        given = {}
        if order is not None:
            cholmod.options["nmethods"] = 1  # the given order only (by default AMD is tried too)
            given["p"] = matrix(np.asarray(order, np.int64), tc="i")
        try:
            factor = cholmod.symbolic(A, uplo="L", **given)
            cholmod.numeric(A, factor)
            cholmod.solve(factor, B)
            return np.array(B)
        except ArithmeticError:
            pass
        finally:
            cholmod.options.clear()
            cholmod.options.update(saved)

    full = sp.coo_matrix((values, (rows, cols)), shape=(k, k)).tocsc()
    full = (full + sp.tril(full, k=-1).T).tocsc()
    return np.asarray(spsolve(full, b)).reshape(b.shape)


def heat_distance(positions: np.ndarray, faces: np.ndarray, sources: np.ndarray) -> np.ndarray:
    """Geodesic distance (n,) float64 from a vertex set by the heat method (potpourri3d).

    Vertices not referenced by any face, or in a component with no source, get +inf.
    """
    import potpourri3d as pp3d  # noqa: PLC0415 (loaded on use)

    n = len(positions)
    used = np.zeros(n, bool)
    used[np.asarray(faces).ravel()] = True
    ncomp, label = csgraph.connected_components(adjacency(faces, n), directed=False)
    dist = np.full(n, np.inf)
    sources = np.asarray(sources, dtype=np.int64)
    for c in np.unique(label[sources]):
        verts = np.flatnonzero((label == c) & used)
        if len(verts) < 3:
            dist[verts] = 0.0
            continue
        local = np.full(n, -1)
        local[verts] = np.arange(len(verts))
        fc = local[np.asarray(faces)]
        fc = fc[(fc >= 0).all(axis=1)]
        solver = pp3d.MeshHeatMethodDistanceSolver(np.asarray(positions, np.float64)[verts], fc)
        src = local[sources[label[sources] == c]]
        dist[verts] = solver.compute_distance_multisource(src)
    return dist


def _fmm(faces: np.ndarray, positions: np.ndarray, known: np.ndarray, vals: np.ndarray, passes: int) -> np.ndarray:
    n = len(positions)
    f = np.asarray(faces, dtype=np.int64)
    e = edges(f)
    adj = adjacency(f, n)
    known = _zero_unreachable(adj, known, vals)
    sources = np.flatnonzero(known)
    if len(sources) == n:
        return vals
    dist = heat_distance(positions, f, sources)
    dist[known] = 0.0
    dist = np.where(np.isfinite(dist), dist, 0.0)
    # Upwind weights: an edge j -> i carries j's value to i in proportion to the distance it
    # descends per unit length (the cosine between the edge and the distance gradient).
    both = np.concatenate([e, e[:, ::-1]])
    i, j = both[:, 0], both[:, 1]
    length = np.linalg.norm(positions[i] - positions[j], axis=1)
    descent = (dist[i] - dist[j]) / np.maximum(length, 1e-300)
    upwind = descent > 0
    w = sp.coo_matrix((descent[upwind], (i[upwind], j[upwind])), shape=(n, n)).tocsr()
    plain = adj
    upwind_mask = (w > 0).astype(np.float64).tocsr()
    up_count = np.diff(w.indptr)
    done = known.copy()
    order = np.flatnonzero(~done)
    # Vectorised rounds: a vertex is ready once all its upwind neighbours are known. The heat
    # method's distance can have spurious local minima (no upwind neighbour); when nothing
    # is ready, vertices with any known neighbour take their mean instead.
    while len(order):
        known_f = done.astype(np.float64)
        n_known_up = upwind_mask[order] @ known_f
        ready = (up_count[order] > 0) & (n_known_up == up_count[order])
        source = w
        if not ready.any():
            ready = (plain[order] @ known_f) > 0
            source = plain
            if not ready.any():
                vals[order] = 0.0
                break
        sel = order[ready]
        a = source[sel].multiply(known_f[None, :]).tocsr()
        vals[sel] = (a @ vals) / np.asarray(a.sum(axis=1))
        done[sel] = True
        order = order[~ready]
    # A few averaging passes keep assigned (known) values fixed.
    deg = np.asarray(plain.sum(axis=1)).ravel()
    free = np.flatnonzero(~known & (deg > 0))
    for _ in range(max(0, int(passes))):
        vals[free] = (plain[free] @ vals) / deg[free, None]
    return vals
