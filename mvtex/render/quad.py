"""A textured planar quad (a printed calibration board, a photo) seen by a pinhole camera:
`QuadRenderer`, drawn with moderngl through the same projection as every mvtex render, so
its pixels follow the OpenCV convention (DESIGN §3)."""

from __future__ import annotations

import numpy as np

from mvtex.data.camera import Camera
from mvtex.render.context import GLContext
from mvtex.render.raster import clip_from_camera


class QuadRenderer:
    """Draws one grey image mapped onto a planar quad, mipmapped and anisotropically
    filtered, in a `GLContext` (given, or its own, freed by `release`).

    Args:
        image: (h,w) uint8, row 0 on the quad's first edge (`corners[0]` to `corners[1]`).
        corners: (4,3) float the quad's corners in its own frame, in the order (x0, y0),
            (x1, y0), (x1, y1), (x0, y1): texture (0,0), (1,0), (1,1), (0,1).
        ctx: the GL context to draw in (default: a new one).
    """

    def __init__(self, image: np.ndarray, corners: np.ndarray, ctx: GLContext | None = None):
        import moderngl  # noqa: PLC0415 (loaded on use)

        self._owns_gl = ctx is None
        self.gl = GLContext() if ctx is None else ctx
        self.corners = np.asarray(corners, dtype=np.float64).reshape(4, 3)
        texcoords = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], dtype=np.float64)
        order = [0, 1, 2, 0, 2, 3]
        quad = np.hstack([self.corners[order], texcoords[order]]).astype("f4")
        self._targets: dict[tuple[int, int], object] = {}
        mgl = self.gl.mgl
        with mgl:
            self._texture = mgl.texture((image.shape[1], image.shape[0]), 1,
                                        np.ascontiguousarray(image, dtype=np.uint8).tobytes())
            self._texture.build_mipmaps()
            self._texture.filter = (moderngl.LINEAR_MIPMAP_LINEAR, moderngl.LINEAR)
            self._texture.anisotropy = 16.0
            self._texture.repeat_x = self._texture.repeat_y = False
            self._program = self.gl._program("quad.vert.glsl", "quad.frag.glsl")
            self._vbo = mgl.buffer(quad.tobytes())
            self._vao = mgl.vertex_array(self._program, [(self._vbo, "3f 2f", "in_local", "in_texcoord")])

    def draw(self, camera: Camera, cam_from_local: np.ndarray, background: int) -> np.ndarray:
        """The quad seen by a pinhole camera (its K and size; R, t are not used).

        Args:
            camera: the camera.
            cam_from_local: (4,4) float64, the quad's frame -> the camera's.
            background: grey level where the quad is not seen.

        Returns:
            (H,W) uint8, OpenCV row order.

        Raises:
            ValueError: the quad is (partly) behind the camera.
        """
        import moderngl  # noqa: PLC0415 (loaded on use)

        z = self.corners @ cam_from_local[2, :3] + cam_from_local[2, 3]
        if z.min() <= 0:
            raise ValueError(f"camera {camera.name!r}: the quad is (partly) behind the camera")
        near, far = max(1e-3, 0.5 * float(z.min())), 2.0 * float(z.max()) + 1e-3
        mgl = self.gl.mgl
        with mgl:
            self._program["clip_from_cam"].write(clip_from_camera(camera, near, far).T.astype("f4").tobytes())
            self._program["cam_from_local"].write(np.asarray(cam_from_local).T.astype("f4").tobytes())
            self._program["image"].value = 0
            size = (camera.width, camera.height)
            if size not in self._targets:  # kept for the renderer's life, one per image size
                self._targets[size] = mgl.framebuffer(color_attachments=[mgl.texture(size, 1)])
            fbo = self._targets[size]
            fbo.use()
            fbo.clear(background / 255.0, background / 255.0, background / 255.0, 1.0)
            mgl.disable(moderngl.CULL_FACE | moderngl.DEPTH_TEST)
            self._texture.use(0)
            self._vao.render(moderngl.TRIANGLES)
            return np.frombuffer(fbo.read(components=1), dtype=np.uint8).reshape(camera.height, camera.width).copy()

    def release(self) -> None:
        """Free this renderer's GL objects, and its context if it made it."""
        if self._owns_gl:
            self.gl.release()  # everything made in it goes with it
            return
        with self.gl.mgl:
            for fbo in self._targets.values():
                for attachment in fbo.color_attachments:
                    attachment.release()
                fbo.release()
            for obj in (self._vao, self._vbo, self._texture):
                obj.release()
        self._targets.clear()
