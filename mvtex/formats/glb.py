"""GLB export (trimesh): meshes side by side (the report's 3-D view of the reconstruction),
and the scene of `mvtex export` (a textured mesh with one texcoord set per camera, its body and
its cameras).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from mvtex.util.output import atomic_path


def export_glb(path: str | os.PathLike, meshes: Sequence[tuple[str, np.ndarray, np.ndarray, np.ndarray]],
               spacing: float = 1.25, body: tuple[np.ndarray, np.ndarray, Sequence[int]] | None = None) -> Path:
    """Write meshes side by side (along x, in order) into one GLB, atomically.

    Args:
        meshes: (name, positions (n,3) m, faces (m,3) int, vertex colours (n,3) uint8).
        spacing: distance between neighbours, in units of the widest mesh's x extent.
        body: optional (positions (nb,3), faces (mb,3), rgb) of the wearer, drawn in one
            colour inside every mesh (moved with it), so that each is seen worn.

    Positions are kept in world axes, only centred: the built-in data is y-up with the
    cameras on +z, glTF's convention, so a viewer opens on the garment's front.
    """
    import trimesh  # noqa: PLC0415 (loaded on use)

    width = max(float(np.ptp(np.asarray(p)[:, 0])) for _, p, _, _ in meshes)
    scene = trimesh.Scene()
    for i, (name, positions, faces, colors) in enumerate(meshes):
        p = np.asarray(positions, np.float64)
        p = p - p.mean(axis=0)
        p[:, 0] += (i - (len(meshes) - 1) / 2) * spacing * width
        rgba = np.hstack([np.asarray(colors, np.uint8), np.full((len(p), 1), 255, np.uint8)])
        mesh = trimesh.Trimesh(vertices=p, faces=np.asarray(faces, np.int64), vertex_colors=rgba, process=False)
        scene.add_geometry(mesh, node_name=name, geom_name=name)
        if body is not None:
            shift = p[0] - np.asarray(positions, np.float64)[0]
            b = np.asarray(body[0], np.float64) + shift
            colour = np.tile(np.append(np.asarray(body[2], np.uint8), 255), (len(b), 1))
            worn = trimesh.Trimesh(vertices=b, faces=np.asarray(body[1], np.int64), vertex_colors=colour, process=False)
            scene.add_geometry(worn, node_name=f"{name}_body", geom_name=f"{name}_body")
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(scene.export(file_type="glb"))
    return path


@dataclass(frozen=True)
class SceneCamera:
    """A camera node of `scene_glb`: an OpenCV pinhole camera and the texcoord set it sees.

    Attributes:
        name: the node's name. width, height: image size (px).
        K: (3,3) intrinsics (OpenCV pixel centres). R, t: world-to-camera, x_cam = R X + t.
        texcoord: the index k of the mesh's TEXCOORD_k that holds this camera's texture coordinates.
    """

    name: str
    width: int
    height: int
    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    texcoord: int


def gl_camera_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(4,4) world-from-camera matrix of a glTF camera (looking down -Z, +Y up) that sees what
    the OpenCV camera (R, t) sees: the glTF camera's axes are diag(1, -1, -1) of OpenCV's."""
    R = np.asarray(R, np.float64)
    pose = np.eye(4)
    pose[:3, :3] = R.T @ np.diag([1.0, -1.0, -1.0])
    pose[:3, 3] = -R.T @ np.asarray(t, np.float64).reshape(3)
    return pose


def scene_glb(path: str | os.PathLike, *, positions: np.ndarray, faces: np.ndarray, normals: np.ndarray,
              texcoords: Sequence[np.ndarray], texture: np.ndarray, cameras: Sequence[SceneCamera],
              body: tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int, int]] | None = None,
              extras: dict | None = None) -> Path:
    """Write a textured mesh with several texture-coordinate sets, its body and its cameras as
    one GLB (glTF 2.0, trimesh), atomically.

    The mesh is the node "cloth": POSITION, NORMAL, TEXCOORD_0 ... TEXCOORD_{k-1} (`texcoords`
    in order), a material whose base colour is `texture` (double-sided, not metallic, fully
    rough). The body, if any, is the node "body" in one grey. Each camera is a root node
    holding a perspective glTF camera (vertical field of view and aspect ratio from K; glTF
    has no principal point) with `extras.mvtex` = {"camera", "texcoord", "attribute", "K",
    "width", "height"}; `extras` goes to the scene's `extras.mvtex`.

    Texture coordinates are mvtex's (v up, texel row 0 at v ≈ 0): they are written as glTF's
    (u, 1 - v) and the image with its rows flipped, so that glTF readers sample the same texel.

    Args:
        positions: (n,3) world positions (m). faces: (m,3) int. normals: (n,3) unit vertex normals.
        texcoords: k arrays (n,2) of per-vertex uv.
        texture: (H,W,3) uint8 RGB, row 0 at v ≈ 0.
        cameras: the camera nodes.
        body: (positions (nb,3), faces (mb,3), normals (nb,3), RGB) or None.
        extras: JSON-serialisable data about the scene.
    """
    import trimesh  # noqa: PLC0415 (loaded on use)
    from PIL import Image  # noqa: PLC0415 (loaded on use)

    positions = np.asarray(positions, np.float64)
    n = len(positions)
    uv = [np.asarray(t, np.float64) for t in texcoords]
    if not uv or any(t.shape != (n, 2) for t in uv):
        raise ValueError(f"texcoords must be a non-empty list of ({n}, 2) arrays")
    image = Image.fromarray(np.ascontiguousarray(np.asarray(texture, np.uint8)[::-1]), mode="RGB")
    material = trimesh.visual.material.PBRMaterial(name="fabric", baseColorTexture=image, metallicFactor=0.0,
                                                   roughnessFactor=1.0, doubleSided=True)
    cloth = trimesh.Trimesh(vertices=positions, faces=np.asarray(faces, np.int64), process=False)
    cloth.visual = trimesh.visual.TextureVisuals(uv=uv[0], material=material)  # trimesh writes (u, 1 - v)
    cloth.vertex_normals = np.asarray(normals, np.float64)
    for k, t in enumerate(uv[1:], start=1):
        cloth.vertex_attributes[f"TEXCOORD_{k}"] = np.stack([t[:, 0], 1.0 - t[:, 1]], axis=1).astype(np.float32)
    scene = trimesh.Scene()
    scene.add_geometry(cloth, node_name="cloth", geom_name="cloth")
    if body is not None:
        grey = [_linear(c / 255.0) for c in body[3]] + [1.0]
        skin = trimesh.visual.material.PBRMaterial(name="body", baseColorFactor=grey, metallicFactor=0.0,
                                                   roughnessFactor=1.0, doubleSided=True)
        mesh = trimesh.Trimesh(vertices=np.asarray(body[0], np.float64), faces=np.asarray(body[1], np.int64),
                               process=False)
        mesh.visual = trimesh.visual.TextureVisuals(material=skin)
        mesh.vertex_normals = np.asarray(body[2], np.float64)
        scene.add_geometry(mesh, node_name="body", geom_name="body")

    def finish(tree: dict) -> None:
        """trimesh writes the extra texcoord sets as application attributes ("_TEXCOORD_k"):
        name them as glTF's texcoord sets; add the cameras and the scene's extras."""
        for mesh in tree["meshes"]:
            for primitive in mesh["primitives"]:
                attributes = primitive["attributes"]
                for key in [k for k in attributes if k.startswith("_TEXCOORD_")]:
                    attributes[key[1:]] = attributes.pop(key)
        for mesh in tree["meshes"]:  # the buffer views' GL targets (the validator's hint)
            for primitive in mesh["primitives"]:
                for key, index in list(primitive["attributes"].items()) + [("indices", primitive.get("indices"))]:
                    if index is not None and "bufferView" in tree["accessors"][index]:
                        view = tree["bufferViews"][tree["accessors"][index]["bufferView"]]
                        view["target"] = 34963 if key == "indices" else 34962  # ELEMENT_ARRAY_BUFFER, ARRAY_BUFFER
        tree.setdefault("cameras", [])
        roots = tree["scenes"][0].setdefault("nodes", [])
        for cam in cameras:
            K = np.asarray(cam.K, np.float64)
            tree["cameras"].append({"name": cam.name, "type": "perspective", "perspective": {
                "yfov": float(2 * np.arctan(cam.height / (2 * K[1, 1]))),
                "aspectRatio": float(cam.width * K[1, 1] / (cam.height * K[0, 0])),
                "znear": 0.01}})
            tree["nodes"].append({"name": cam.name, "camera": len(tree["cameras"]) - 1,
                                  "matrix": gl_camera_pose(cam.R, cam.t).T.ravel().tolist(),
                                  "extras": {"mvtex": {"camera": cam.name, "texcoord": int(cam.texcoord),
                                                       "attribute": f"TEXCOORD_{int(cam.texcoord)}",
                                                       "K": K.tolist(), "width": int(cam.width),
                                                       "height": int(cam.height)}}})
            roots.append(len(tree["nodes"]) - 1)
        tree["scenes"][0]["extras"] = {"mvtex": extras or {}}
        tree["asset"]["generator"] = "mvtex (trimesh)"

    data = trimesh.exchange.gltf.export_glb(scene, include_normals=True, tree_postprocessor=finish)
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)
    return path


def _linear(c: float) -> float:
    """An sRGB colour component (0..1) in linear light, as glTF's colour factors are."""
    return c / 12.92 if c <= 0.04045 else ((c + 0.055) / 1.055) ** 2.4
