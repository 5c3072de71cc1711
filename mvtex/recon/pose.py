"""`mvtex triangulate`: the reconstruction of one dataset pose from a texcoord set, its report
and its output directory.
"""

from __future__ import annotations

import os
from dataclasses import replace

import numpy as np

from mvtex.data.dataset import as_dataset
from mvtex.data.rig import Rig, as_rig, check_outside_body
from mvtex.data.texcoords import as_texcoords
from mvtex.recon.export import export_reconstruction
from mvtex.recon.options import check_observation_count
from mvtex.recon.report import ReconReport, reconstruction_report
from mvtex.recon.triangulate import ReconOptions, reconstruct
from mvtex.render.context import GLContext
from mvtex.util.checks import as_index, as_path, check_instance
from mvtex.util.errors import InputError
from mvtex.util.output import writer


@writer("triangulate", inputs=lambda a: (a["dataset"], a["texcoords"]))
def triangulate_pose(dataset, rig: Rig, texcoords, pose: int, out: str | os.PathLike | None,
                     options: ReconOptions = ReconOptions(), progress: bool = True, *,
                     ctx: GLContext | None = None, overwrite: bool = False) -> ReconReport:
    """`mvtex triangulate`: reconstruct one pose of a dataset from a texcoord set.

    Args:
        dataset: a `mvtex.data.dataset.Dataset`; an inference set (no gt) gives a report
            whose measures against gt are None, and no comparison.png.
        rig: the cameras; those of the texcoord set are used (≥ 2 needed).
        texcoords: a `mvtex.data.texcoords.TexcoordSet` for this dataset.
        pose: dataset pose index (must be one of the texcoord set's poses).
        out: output directory (written atomically by `mvtex.recon.export.export_reconstruction`),
            or None for the numbers only.
        options: see ReconOptions. On a corrected set (`mvtex.tsnn.correct.correct`) the
            corrected mesh is the prior, fused with its σ (`ReconOptions.use_prior`), and
            the report also holds the errors of the mesh before the correction.
        progress: progress bars on stderr.
        overwrite: replace another command's output at `out` (never files mvtex did not
            write, never an input: the writer policy of `mvtex.util.output`).
        ctx: the GL context (`mvtex.render.context.GLContext`); one is made when None.

    Returns:
        The `mvtex.recon.report.ReconReport` (its `to_json()` is report.json, DESIGN §7).

    Raises:
        InputError: a pose outside the dataset or the texcoord set, a texcoord set made
            for another mesh, fewer than 2 cameras shared by rig and texcoord set.
    """

    pose = as_index(pose, "pose")  # the plain arguments first, before any file is opened
    out = as_path(out, "out", optional=True)
    check_instance(options, ReconOptions, "options")
    dataset = as_dataset(dataset)
    rig = as_rig(rig)
    texcoords = as_texcoords(texcoords)
    if ctx is None:

        with GLContext() as own:
            return triangulate_pose(dataset, rig, texcoords, pose, out, options, progress, ctx=own)
    pose = int(pose)
    if not 0 <= pose < dataset.num_poses:
        raise InputError(dataset.path, f"pose {pose} is outside [0, {dataset.num_poses})")
    texcoords.row(pose)  # InputError if the set lacks this pose
    texcoords.check_dataset(dataset)
    names = [c for c in texcoords.cameras if c in rig.names]
    texcoords.check_rig(rig, cameras=names)
    if len(names) < 2:
        raise InputError(texcoords.path, f"triangulation needs ≥ 2 cameras present in both the texcoord set "
                         f"({', '.join(texcoords.cameras)}) and the rig ({', '.join(rig.names)})")
    check_observation_count(dataset.num_vertices, len(names), texcoords.path)  # before anything is allocated
    sub_rig = rig.select(names)
    check_outside_body(sub_rig, dataset, [pose])
    prior = dataset.geometry_uncertainty is not None and options.use_prior
    options = options.for_source(texcoords.source, prior=prior)
    X_N = texcoords.positions(np.asarray(dataset.inferred[pose], np.float64))
    prior_sigma = np.asarray(dataset.geometry_uncertainty[pose], np.float64) if prior else None
    T = {c: np.asarray(texcoords.texcoords(c, pose), np.float64) for c in names}
    assigned = {c: texcoords.assigned(c, pose) for c in names}
    uncertainty = {c: texcoords.uncertainty(c, pose) for c in names}
    uncertainty = uncertainty if all(u is not None for u in uncertainty.values()) else None
    rest = None if dataset.rest is None else np.asarray(dataset.rest, np.float64)
    body = None if dataset.body is None else (dataset.body.pose(pose), dataset.body.faces)
    rec = reconstruct(dataset.uv, X_N, texcoords.faces, texcoords.uv, T, sub_rig, options,
                      gt_faces=dataset.faces, assigned=assigned, rest=rest, body=body, uncertainty=uncertainty,
                      prior_sigma=prior_sigma, progress=progress, ctx=ctx)
    gt = np.asarray(dataset.gt[pose], np.float64) if dataset.has_gt else None
    original = None if dataset.original_inferred is None else np.asarray(dataset.original_inferred[pose], np.float64)
    report = replace(reconstruction_report(rec, gt, dataset.faces, rest, pose, options, original),
                     cameras=tuple(names),
                     texcoords=str(texcoords.path), source=texcoords.source, subdiv=texcoords.subdiv)
    if out is not None:
        # The command's one edge up the layers: its output directory is the export module's.

        export_reconstruction(out, rec, sub_rig, faces=dataset.faces, uv=dataset.uv, gt=gt, rest=rest,
                              inferred_mesh=(X_N, texcoords.faces, T), report=report.to_json(), options=options,
                              progress=progress, ctx=ctx, body=body)
    return report
