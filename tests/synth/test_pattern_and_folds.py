"""The pattern mesher and the fold field of mvtex.synth, against closed forms: a polygon's
area and border, and a fold on a flat sheet whose cross-sections keep their length."""

from __future__ import annotations

import numpy as np

from mvtex.synth.folds import Fold, fold_field
from mvtex.synth.pattern import mesh_pattern, sample_curve


def test_an_l_shaped_piece_is_meshed_inside_its_border():
    corners = np.array([(0, 0), (0.3, 0), (0.3, 0.1), (0.1, 0.1), (0.1, 0.25), (0, 0.25)], dtype=np.float64)
    spacing = 0.02
    boundary = np.concatenate([sample_curve(np.linspace(p, q, 20), spacing) for p, q in
                               zip(corners, np.roll(corners, -1, axis=0))])
    points, faces = mesh_pattern(boundary, spacing)
    np.testing.assert_array_equal(points[: len(boundary)], boundary)
    p = points[faces]
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    area = 0.5 * (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    assert np.all(area > 0)  # counter-clockwise
    assert abs(area.sum() - (0.3 * 0.1 + 0.1 * 0.15)) < 1e-12  # covers the polygon exactly
    # The border of the mesh is the polygon: boundary edges are the consecutive samples.
    pairs = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    edges, counts = np.unique(pairs, axis=0, return_counts=True)
    border = {tuple(e) for e in edges[counts == 1]}
    expected = {tuple(sorted((i, (i + 1) % len(boundary)))) for i in range(len(boundary))}
    assert border == expected
    # Near-equilateral: no sliver.
    lengths = np.linalg.norm(p - np.roll(p, -1, axis=1), axis=2)
    angles = np.arccos(np.clip((lengths[:, [1, 2, 0]] ** 2 + lengths[:, [2, 0, 1]] ** 2 - lengths ** 2)
                               / (2 * lengths[:, [1, 2, 0]] * lengths[:, [2, 0, 1]]), -1, 1))
    assert np.degrees(angles.min()) > 20 and 0.8 * spacing < np.median(lengths) < 1.2 * spacing


def test_a_fold_on_a_flat_sheet_keeps_lengths_and_moves_only_its_free_side():
    fold = Fold("sheet", 0.0, 0.0, np.pi / 2, 0.06, 1.4, 0.45, 0.2)  # a ridge along x, normal +y
    y = np.linspace(-0.2, 0.1, 3001)
    for x0 in (0.0, 0.1):  # the middle of the ridge and where it fades
        support, slide, offset, peak = fold_field(fold, np.full(len(y), x0), y)
        moved = np.zeros((len(y), 2))
        moved[support] = slide
        height = np.zeros(len(y))
        height[support] = offset
        # The sheet is the plane z = 0 with material (x, y): the folded cross-section is
        # (y + slide_y, offset); its length equals the material's.
        curve = np.stack([y + moved[:, 1], height], axis=1)
        length = np.linalg.norm(np.diff(curve, axis=0), axis=1).sum()
        assert abs(length - np.ptp(y)) < 5e-4 * np.ptp(y)  # the tabulated profile, interpolated
        assert np.abs(moved[:, 0]).max() < 1e-15  # material slides along the normal only (cos(pi/2) aside)
        above = y > fold.reach
        assert np.all(moved[above] == 0.0) and np.all(height[above] == 0.0)  # the +n side stays
    support, slide, offset, peak = fold_field(fold, np.zeros(len(y)), y)
    gathered = slide[np.argmin(y[support]), 1]
    assert gathered > 0.005  # the far -n side moves towards the fold by what it gathers
    assert 0.01 < np.ptp(offset) < 0.03 and offset[np.argmin(np.abs(y[support]))] == offset.max()  # a ridge
    assert np.degrees(peak) > 60
