"""Textured triangle meshes rasterized by OpenGL (moderngl) on a headless EGL context.

The camera is the pinhole of eq. 10 (Zhang et al. 2006): a camera-frame point ``X = (x, y, z)``
mm (x right, y down, z away from the camera) lands on pixel ``(u, v) = (fx x / z + s y / z + cx,
fy y / z + cy)``, origin at the centre of the top-left pixel (OpenCV's convention). The vertex
shader maps ``(u, v)`` to normalized device coordinates with ``v`` increasing with NDC ``y``, so
framebuffer row 0 is image row 0 and no flip is needed; in that mapping a triangle whose vertices
run counter-clockwise on screen (positive signed area with y down, the facegen convention) is
GL's counter-clockwise front face.

Two passes per image: the colour pass into a multisampled framebuffer (MSAA, anti-aliased edges
and a coverage alpha), resolved; the depth pass into a single-sample ``R32F`` target that holds
the perspective-correct camera depth ``z`` (mm) of the nearest surface, so a pixel's depth is
never an average across an edge. Both passes use the z-buffer.

On a machine without a GPU, Mesa's llvmpipe runs the same code on the CPU (``libegl-mesa0``,
``libgl1-mesa-dri``; ``.ci/install-egl``).
"""

from __future__ import annotations

import numpy as np

__all__ = ["MeshRenderer", "gl_context"]

_VERTEX = """
#version 330
uniform mat3 A;          // intrinsics, px
uniform vec2 size;       // (W, H) px
uniform vec2 near_far;   // clipping depths, mm
in vec3 position;        // camera frame, mm
in vec3 uvw;             // (s w, t w, w): texture coordinates in [0, 1] times the projective weight w
out vec3 v_uvw;
out float v_depth;
void main() {
    vec3 p = A * position;                       // (u z, v z, z): column-major like GLSL
    float z = position.z;
    vec2 ndc_z = 2.0 * (p.xy + 0.5 * z) / size - z; // (2 (u + 0.5) / W - 1) z, same for v
    float n = near_far.x, f = near_far.y;
    float clip_z = (f + n) / (f - n) * z - 2.0 * f * n / (f - n);
    gl_Position = vec4(ndc_z, clip_z, z);
    v_uvw = uvw;
    v_depth = z;
}
"""

_COLOUR = """
#version 330
uniform sampler2D tex;
in vec3 v_uvw;
in float v_depth;
out vec4 colour;
void main() {
    vec4 c = texture(tex, v_uvw.xy / v_uvw.z);   // projective lookup (w = 1: plain perspective-correct)
    colour = vec4(c.rgb * c.a, c.a);             // premultiplied (associated) alpha
}
"""

_DEPTH = """
#version 330
in float v_depth;
out float depth;
void main() {
    depth = v_depth;
}
"""


def gl_context():
    """A standalone OpenGL 3.3 context on EGL (no display server); Mesa's llvmpipe without a GPU.

    Raises
    ------
    RuntimeError
        No EGL/OpenGL library can be loaded (install ``libegl1 libegl-mesa0 libgl1-mesa-dri``,
        ``.ci/install-egl``).
    """
    import moderngl

    try:
        return moderngl.create_standalone_context(backend="egl", require=330)
    except Exception as exc:  # moderngl raises plain Exception for a missing EGL driver
        raise RuntimeError(
            f"no headless OpenGL context (EGL): {exc}; install libegl1 libegl-mesa0 libgl1-mesa-dri (.ci/install-egl)"
        ) from exc


class MeshRenderer:
    """Render textured meshes at one image size with one GL context.

    Parameters
    ----------
    size : (W, H) int
        Output image size, px.
    samples : int
        MSAA samples per pixel (0 or 1: aliased edges); clamped to what the driver offers
        (llvmpipe: 4).
    near, far : float
        Clipping depths, mm from the camera.
    """

    def __init__(self, size: tuple[int, int], *, samples: int = 4, near: float = 10.0, far: float = 1.0e5) -> None:
        W, H = (int(v) for v in size)
        if W < 1 or H < 1:
            raise ValueError(f"size must be positive (W, H), got {size}")
        if not 0 < near < far:
            raise ValueError(f"expected 0 < near < far, got near={near}, far={far}")
        self.size = (W, H)
        self.ctx = gl_context()
        self.samples = int(min(max(samples, 0), self.ctx.max_samples)) if samples > 1 else 0
        self._colour = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_COLOUR)
        self._depth = self.ctx.program(vertex_shader=_VERTEX, fragment_shader=_DEPTH)
        for prog in (self._colour, self._depth):
            prog["size"].value = (float(W), float(H))
            prog["near_far"].value = (float(near), float(far))
        ms = self.samples
        self._fbo_ms = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((W, H), 4, samples=ms, dtype="f4")],
            depth_attachment=self.ctx.depth_renderbuffer((W, H), samples=ms),
        )
        self._fbo_rgba = self.ctx.framebuffer(color_attachments=[self.ctx.renderbuffer((W, H), 4, dtype="f4")])
        self._fbo_z = self.ctx.framebuffer(
            color_attachments=[self.ctx.renderbuffer((W, H), 1, dtype="f4")],
            depth_attachment=self.ctx.depth_renderbuffer((W, H)),
        )

    def render(
        self,
        vertices: np.ndarray,
        triangles: np.ndarray,
        uv: np.ndarray,
        texture: np.ndarray,
        A: np.ndarray,
        *,
        cull_back: bool = False,
        uv_depth: np.ndarray | None = None,
    ) -> tuple[np.ndarray | tuple[np.ndarray, ...], np.ndarray]:
        """Rasterize one textured mesh.

        Parameters
        ----------
        vertices : (V, 3) float
            Camera-frame positions, mm (x right, y down, z away from the camera).
        triangles : (F, 3) int
            Vertex indices; counter-clockwise on screen = front facing.
        uv : (V, 2) float
            Texture positions in pixels of ``texture`` (x right, y down, origin at the centre of
            its top-left pixel).
        texture : (h, w, 3) or (h, w, 4) float or uint8, or a tuple of such (one size)
            Colours (any encoding: interpolated as given) and optional alpha; uint8 is divided by
            255. A tuple renders each over the same mesh (one colour pass each, one depth pass).
        A : (3, 3) float
            Intrinsics of eq. 10 for the output size, px.
        cull_back : bool
            Drop back-facing triangles (clockwise on screen).
        uv_depth : (V,) float, optional
            Projective texturing: each vertex's depth in the view the texture was taken from (the
            mesh at rest); a surface point takes the texture at ``sum w_i z_i uv_i / sum w_i z_i``
            (``w_i`` its 3D barycentric weights), its projection in that view, so a mesh rendered at
            rest reproduces its texture exactly. Without it, ``uv`` is interpolated
            perspective-correctly (``z_i = 1``).

        Returns
        -------
        rgba : (H, W, 4) float32, or a tuple of them (one per texture)
            Premultiplied colour and alpha (MSAA coverage times the texture's alpha); 0 where no
            triangle is.
        depth : (H, W) float32
            Camera depth ``z`` of the nearest surface at each pixel centre, mm; ``inf`` where no
            triangle covers the centre.
        """
        import moderngl

        verts = np.asarray(vertices, np.float64)
        tri = np.asarray(triangles)
        uvs = np.asarray(uv, np.float64)
        textures = tuple(np.asarray(t) for t in texture) if isinstance(texture, tuple) else (np.asarray(texture),)
        tex = textures[0]
        if verts.ndim != 2 or verts.shape[1] != 3:
            raise ValueError(f"vertices must be (V, 3), got {verts.shape}")
        if tri.ndim != 2 or tri.shape[1] != 3 or not np.issubdtype(tri.dtype, np.integer):
            raise ValueError(f"triangles must be (F, 3) integers, got {tri.shape} {tri.dtype}")
        if tri.size and (tri.min() < 0 or tri.max() >= len(verts)):
            raise ValueError(f"triangles index vertices 0..{len(verts) - 1}, got {tri.min()}..{tri.max()}")
        if uvs.shape != (len(verts), 2):
            raise ValueError(f"uv must be ({len(verts)}, 2), got {uvs.shape}")
        if any(t.ndim != 3 or t.shape[2] not in (3, 4) or t.shape[:2] != tex.shape[:2] for t in textures):
            raise ValueError(f"textures must be (h, w, 3) or (h, w, 4) of one size, got {[t.shape for t in textures]}")
        w0 = np.ones(len(verts)) if uv_depth is None else np.asarray(uv_depth, np.float64)
        if w0.shape != (len(verts),) or not np.all(w0 > 0):
            raise ValueError(f"uv_depth must be ({len(verts)},) positive, got {w0.shape}")
        if np.asarray(A).shape != (3, 3):
            raise ValueError(f"A must be (3, 3), got {np.asarray(A).shape}")
        h, w = tex.shape[:2]

        def rgba_texture(t: np.ndarray) -> np.ndarray:
            t = t.astype(np.float32) / 255.0 if t.dtype == np.uint8 else t.astype(np.float32)
            return np.concatenate([t, np.ones((h, w, 1), np.float32)], axis=2) if t.shape[2] == 3 else t

        st = (uvs + 0.5) / np.array([w, h])
        data = np.hstack([verts, st * w0[:, None], w0[:, None]]).astype(np.float32)
        W, H = self.size
        ctx = self.ctx
        colours = []
        with ctx:  # make this renderer's context current (several renderers may coexist)
            vbo = ctx.buffer(data.tobytes())
            ibo = ctx.buffer(np.ascontiguousarray(tri, np.int32).tobytes())
            try:
                ctx.enable(moderngl.DEPTH_TEST)
                ctx.front_face = "ccw"
                if cull_back:
                    ctx.enable(moderngl.CULL_FACE)
                    ctx.cull_face = "back"
                else:
                    ctx.disable(moderngl.CULL_FACE)
                a = np.asarray(A, np.float32)
                for prog in (self._colour, self._depth):
                    prog["A"].write(np.ascontiguousarray(a.T).tobytes())  # GLSL mat3 is column-major
                self._colour["tex"].value = 0
                vao = ctx.vertex_array(self._colour, [(vbo, "3f 3f", "position", "uvw")], index_buffer=ibo)
                for t in textures:
                    gl_tex = ctx.texture((w, h), 4, np.ascontiguousarray(rgba_texture(t)).tobytes(), dtype="f4")
                    gl_tex.filter = (moderngl.LINEAR, moderngl.LINEAR)
                    gl_tex.repeat_x = gl_tex.repeat_y = False
                    gl_tex.use(0)
                    self._fbo_ms.use()
                    self._fbo_ms.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                    vao.render(moderngl.TRIANGLES)
                    ctx.copy_framebuffer(self._fbo_rgba, self._fbo_ms)
                    colours.append(
                        np.frombuffer(self._fbo_rgba.read(components=4, dtype="f4"), np.float32).reshape(H, W, 4).copy()
                    )
                    gl_tex.release()
                vao.release()
                vao = ctx.vertex_array(self._depth, [(vbo, "3f 12x", "position")], index_buffer=ibo)
                self._fbo_z.use()
                self._fbo_z.clear(np.inf, 0.0, 0.0, 0.0, depth=1.0)
                vao.render(moderngl.TRIANGLES)
                depth = np.frombuffer(self._fbo_z.read(components=1, dtype="f4"), np.float32).reshape(H, W)
                vao.release()
            finally:
                vbo.release()
                ibo.release()
        rgba = tuple(colours) if isinstance(texture, tuple) else colours[0]
        return rgba, depth.copy()

    def release(self) -> None:
        """Free the GL context and its framebuffers."""
        self.ctx.release()
