"""What the inferred mesh X_N says, as images over the UV atlas (inputs of the `unet` TSNN).

Per vertex of the dataset mesh and per pose, from the inferred positions alone:

    channel  0-2  position X_N (m, world frame)
             3-5  unit vertex normal (seam copies share one)
             6    strain along u: mean of incident edges' len/rest_len - 1, weighted by the
                  share of each edge along u in the atlas (negative = compressed)
             7    strain along v, the same with v
             8    umbrella curvature: (mean of the welded neighbours - x) . normal / h²,
                  h the mean rest edge length (1/m; positive where the surface bends away
                  from its normal, i.e. in a valley seen from outside)

Values are extended to a subdivided mesh by midpoints (as positions are) and rasterized in
UV with `AtlasSampler.to_image`, so a texel holds the barycentric interpolation of its
triangle's corner values. Per camera the network adds the view (positions and normals in
camera coordinates) itself from channels 0-5 and the camera's extrinsics
(`mvtex.tsnn.model.UNet`), so one set of images serves every camera.

What strain and curvature are measured against (the rest edge lengths and which vertices
are seam copies) is the *reference*: the dataset's rest shape, else the mean of its first
inferred meshes. A trained `unet` keeps the reference it was trained with
(`MeshGeometry.reference_arrays`, geometry.npz in its model directory), so that it sees the
same images of the same inferred mesh in any set of its garment, whatever that set's rest.
"""

from __future__ import annotations

import numpy as np

from mvtex.data.mesh import apply_parent, edges, uniform_laplacian, vertex_normals, weld_groups, welded_adjacency
from mvtex.util.files import read_row

NUM_CHANNELS = 9


CHANNEL_NAMES = ("x", "y", "z", "nx", "ny", "nz", "strain_u", "strain_v", "curvature")


class MeshGeometry:
    """Per-vertex geometry features of one mesh topology, for any number of poses.

    Args:
        faces: (m,3) int dataset faces. uv: (n,2) float T_G.
        rest: (n,3) rest positions; None: the mean edge lengths of `reference` are the rest.
        reference: (k,n,3) positions used for the rest lengths and seam welding when `rest`
            is None (e.g. the training poses' inferred meshes).
    """

    def __init__(self, faces: np.ndarray, uv: np.ndarray, rest: np.ndarray | None = None,
                 reference: np.ndarray | None = None, *, arrays: dict[str, np.ndarray] | None = None):
        self.faces = np.asarray(faces, dtype=np.int64)
        uv = np.asarray(uv, dtype=np.float64)
        self.edges = edges(self.faces)
        n = len(uv)
        if arrays is not None:  # a trained model's reference (`reference_arrays`)
            self.rest_length = np.asarray(arrays["rest_length"], dtype=np.float64)
            self.groups = np.asarray(arrays["groups"], dtype=np.int64)
            if self.rest_length.shape != (len(self.edges),) or self.groups.shape != (n,) \
                    or not np.all(np.isfinite(self.rest_length)) or (self.groups.min(initial=0) < 0) \
                    or self.groups.max(initial=0) >= n:
                raise ValueError(f"reference arrays of another mesh: rest_length {self.rest_length.shape} and "
                                 f"groups {self.groups.shape} for {len(self.edges)} edges and {n} vertices")
        elif rest is None:
            if reference is None:
                raise ValueError("MeshGeometry needs rest positions or reference poses")
            reference = np.asarray(reference, dtype=np.float64)
            self.rest_length = np.linalg.norm(reference[:, self.edges[:, 1]] - reference[:, self.edges[:, 0]],
                                              axis=-1).mean(0)
            self.groups = weld_groups(reference[0])
        else:
            rest = np.asarray(rest, dtype=np.float64)
            self.rest_length = np.linalg.norm(rest[self.edges[:, 1]] - rest[self.edges[:, 0]], axis=-1)
            self.groups = weld_groups(rest)
        self.rest_length = np.maximum(self.rest_length, 1e-12)
        adj = welded_adjacency(self.faces, self.groups)
        deg = np.asarray(adj.sum(axis=1)).ravel()
        # The umbrella operator: (mean of neighbours - x) = -(L x) / deg, L = D - A the welded
        # uniform Laplacian.
        self.umbrella = (-uniform_laplacian(adj)).multiply(1.0 / np.maximum(deg, 1)[:, None]).tocsr()
        self.h2 = float(np.mean(self.rest_length)) ** 2
        # Share of each edge along u and along v in the atlas, pooled per vertex.
        duv = np.abs(uv[self.edges[:, 1]] - uv[self.edges[:, 0]]) ** 2
        duv = duv / np.maximum(duv.sum(1, keepdims=True), 1e-300)
        self.edge_share = duv  # (e,2)
        self.share_sum = np.zeros((n, 2))
        for k in range(2):
            np.add.at(self.share_sum, self.edges[:, k], duv)
        self.num_vertices = n

    @classmethod
    def of_dataset(cls, dataset) -> "MeshGeometry":
        """The geometry of a dataset's mesh, its reference the rest shape or, without one,
        the mean edge lengths of its first (up to 64) inferred meshes."""
        reference = None if dataset.rest is not None else np.asarray(dataset.inferred[:min(64, dataset.num_poses)])
        return cls(dataset.faces, dataset.uv, dataset.rest, reference)

    def reference_arrays(self) -> dict[str, np.ndarray]:
        """What the features are measured against: {"rest_length": (e,) float64 rest edge
        lengths, "groups": (n,) int64 seam groups}; `MeshGeometry(..., arrays=...)` rebuilds
        the same geometry from them."""
        return {"rest_length": self.rest_length.copy(), "groups": self.groups.copy()}

    def features(self, positions: np.ndarray) -> np.ndarray:
        """Per-vertex features of poses.

        Args:
            positions: (K,n,3) inferred positions X_N.

        Returns:
            (K,n,9) float32 (channels in the module docstring).
        """
        p = np.asarray(positions, dtype=np.float64)
        if p.ndim != 3 or p.shape[1:] != (self.num_vertices, 3):
            raise ValueError(f"expected (K,{self.num_vertices},3) positions, got {p.shape}")
        k, n = p.shape[:2]
        out = np.empty((k, n, NUM_CHANNELS), dtype=np.float32)
        strain = np.linalg.norm(p[:, self.edges[:, 1]] - p[:, self.edges[:, 0]], axis=-1) / self.rest_length - 1.0
        for i in range(k):
            normal = vertex_normals(p[i], self.faces, self.groups)
            acc = np.zeros((n, 2))
            weighted = strain[i][:, None] * self.edge_share
            for end in range(2):
                np.add.at(acc, self.edges[:, end], weighted)
            out[i, :, 0:3] = p[i]
            out[i, :, 3:6] = normal
            out[i, :, 6:8] = acc / np.maximum(self.share_sum, 1e-12)
            out[i, :, 8] = np.sum((self.umbrella @ p[i]) * normal, axis=1) / self.h2
        return out


def geometry_images(dataset, poses, sampler, parent: np.ndarray, batch: int = 64,
                    geometry: MeshGeometry | None = None) -> np.ndarray:
    """Geometry images of the inferred meshes of some poses.

    Args:
        dataset: a `mvtex.data.dataset.Dataset` (faces, uv, rest, inferred positions).
        poses: dataset pose indices.
        sampler: `AtlasSampler` of the (possibly subdivided) texcoord mesh.
        parent: (n',2) parent map from the dataset mesh to the sampler's mesh.
        batch: poses rasterized per `to_image` call.
        geometry: the features' reference (a trained model's); None: the dataset's own
            (`MeshGeometry.of_dataset`).

    Returns:
        (K, 9, R, R) float32, row 0 at v ≈ 0; 0 outside the (dilated) charts.
    """
    poses = [int(p) for p in poses]
    geometry = MeshGeometry.of_dataset(dataset) if geometry is None else geometry
    r = sampler.resolution
    out = np.empty((len(poses), NUM_CHANNELS, r, r), dtype=np.float32)
    for start in range(0, len(poses), batch):
        chunk = poses[start:start + batch]
        # Rows through the file (`read_row`): rows read through the dataset's map stay resident.
        rows = np.stack([read_row(dataset.inferred, p) for p in chunk])
        feats = apply_parent(geometry.features(rows), parent)  # (k,n',9)
        flat = feats.transpose(1, 0, 2).reshape(len(parent), -1)  # (n', k*9): one rasterization pass
        images = sampler.to_image(flat).reshape(r, r, len(chunk), NUM_CHANNELS)
        out[start:start + len(chunk)] = images.transpose(2, 3, 0, 1)
    return out
