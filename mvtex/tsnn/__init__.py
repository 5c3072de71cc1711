"""Texture sliding networks (TSNN): a model maps what is known at inference time (the pose,
the inferred mesh X_N, the camera) to the displacements d of a camera.

    atlas     per-vertex values <-> atlas images (rasterize in UV, sample with grid_sample)
    geometry  geometry images of X_N: positions, normals, strain along u and v, curvature
    gp        `gp` (the per-camera default): Gaussian processes of the pose on principal
              components of d
    model     `UNet` (geometry images [+ the camera's view] + pose -> image) and `TSNN`
              (the paper's: pose -> linear -> transposed convolutions -> image)
    train     `train`: one camera's model, or one network for every camera
    predict   `predict`: models -> a texcoord set ("source": "tsnn")
"""
