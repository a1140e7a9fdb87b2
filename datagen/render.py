"""Rendering with pyrender on EGL (Mesa's software renderer works): RGB, z-depth, segmentation,
surface normals and object coordinates.

- RGB: lit by a shadow-casting sun, a fill light and ambient light, 4x multisampled, back faces
  culled as in the label pass (so it shows the surfaces the labels describe), with
  datagen's own lit-pass shaders (datagen/shaders/: textured Lambert + Blinn-Phong, 4-tap shadow
  filter), several times cheaper than pyrender's PBR shader on a software renderer.
- Labels: z-depth and instance segmentation with pyrender's segmentation shaders, drawn into a
  single-sampled framebuffer of the process's own, so every pixel holds the surface hit by the
  ray through its centre.
- Surface (optional layers): one more pass like the label pass (same pixels, same culling) with
  datagen's surface shaders writing the world-space shading normal and the object coordinates
  into two float32 attachments of the same framebuffer.
- pyrender holds the meshes, textures, programs and shadow maps; datagen's own draw loops set
  each frame's uniforms once per program, place each sun's shadow camera once per scene and
  draw the backdrop's shadow depth once per scene (pyrender's loop costs more CPU than llvmpipe's
  drawing: docs/PERFORMANCE.md).
- Motion blur (MOVi-F): the average of sub-frame renders at object poses interpolated between
  physics steps and at the camera pose of the same instant, over a shutter centred on the frame
  time. Labels are always rendered sharp at the frame time.

Pixel convention: our K puts the top-left pixel centre at (0, 0); OpenGL puts it at (0.5, 0.5), so
the principal point handed to pyrender is shifted by half a pixel. pyrender cameras look along -Z
with +Y up (OpenGL), so an OpenCV camera-to-world pose is right-multiplied by diag(1, -1, -1, 1).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import trimesh

from c4d_core import geometry
from c4d_core.system import require_egl
from datagen import textures
from datagen.assets import Asset, AssetLibrary
from datagen.sampling import SceneDescription

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
SHADER_DIR = Path(__file__).resolve().parent / "shaders"


@functools.lru_cache(maxsize=1)
def _pyrender():
    """Import pyrender after selecting EGL (must not be imported before `require_egl`)."""
    require_egl()
    import pyrender

    # pyrender 0.1.45 still uses `np.infty`, which numpy 2 removed (only hit by `Mesh.bounds`
    # of a mesh without primitives); restore the alias instead of patching pyrender.
    if not hasattr(np, "infty"):
        np.infty = np.inf
    return pyrender


@functools.lru_cache(maxsize=1)
def _shader_cache_class():
    """pyrender's shader cache, serving datagen's own lit-pass shaders (datagen/shaders/)."""
    pyrender = _pyrender()

    class DatagenShaders(pyrender.shader_program.ShaderProgramCache):
        # (directional, point) lights of the scene being rendered: compile-time loop bounds of
        # the lit pass, set by SceneRenderer (Mesa unrolls constant loops; a loop bounded by a
        # uniform indexing pyrender's 26 shadow samplers costs 1.5x the whole pass on llvmpipe).
        light_counts = (0, 0)

        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None,
                        defines=None):
            if fragment_shader == "mesh.frag":  # the lit pass; depth, shadow and seg stay
                vertex_shader = str(SHADER_DIR / "mesh.vert")
                fragment_shader = str(SHADER_DIR / "mesh.frag")
                defines = {**(defines or {}), "NUM_DIRECTIONAL_LIGHTS": self.light_counts[0],
                           "NUM_POINT_LIGHTS": self.light_counts[1]}
            elif fragment_shader == "flat.frag":  # pyrender's FLAT pass, unused: the label pass
                # with the surface layers
                vertex_shader = str(SHADER_DIR / "surface.vert")
                fragment_shader = str(SHADER_DIR / "surface.frag")
            return super().get_program(vertex_shader, fragment_shader, geometry_shader, defines)

    return DatagenShaders


@functools.lru_cache(maxsize=1)
def _sun_light_class():
    """A pyrender directional light whose shadow map covers only a square around the origin.

    pyrender fits a directional shadow map to the whole scene, which the 40-unit dome makes so
    coarse that objects cast almost no shadow; this light keeps pyrender's shadow camera pose but
    narrows its orthographic window to `half_width` around the origin (`focus_view`: the origin
    in the shadow camera's view coordinates, set once the scene is built).
    """
    pyrender = _pyrender()

    class WindowedOrthographicCamera(pyrender.OrthographicCamera):
        def __init__(self, centre, **kwargs):
            super().__init__(**kwargs)
            self.centre = centre

        def get_projection_matrix(self, width=None, height=None):
            P = super().get_projection_matrix(width, height)  # (4,4)
            P[0, 3] -= self.centre[0] / self.xmag
            P[1, 3] -= self.centre[1] / self.ymag
            return P

    class SunLight(pyrender.DirectionalLight):
        half_width = 10.0
        focus_view = (0.0, 0.0)

        def _get_shadow_camera(self, scene_scale):
            return WindowedOrthographicCamera(self.focus_view, xmag=self.half_width,
                                              ymag=self.half_width, znear=0.01 * scene_scale,
                                              zfar=2 * scene_scale)

    return SunLight


@functools.lru_cache(maxsize=1)
def _offscreen():
    """The worker process's one offscreen EGL context, resized for each scene.

    Exactly one: deleting a pyrender renderer terminates the EGL display that all its contexts
    share, which would break any other renderer of the process.
    """
    offscreen = _pyrender().OffscreenRenderer(1, 1)
    offscreen._renderer._program_cache = _shader_cache_class()()  # pyrender has no public hook
    return offscreen


_LOCATIONS: dict[int, dict[str, int]] = {}  # GL program id -> uniform name -> location


def _set_uniform(program, name: str, value) -> None:
    """pyrender's `ShaderProgram.set_uniform` (the same float32 conversions, and a uniform the
    program lacks is skipped), with each location looked up once per program instead of on
    every call. value: a float or int, a (n,) float array or a (4,4) matrix (row-major)."""
    from OpenGL import GL as gl

    locations = _LOCATIONS.setdefault(program._program_id, {})
    location = locations.get(name)
    if location is None:
        location = locations[name] = int(gl.glGetUniformLocation(program._program_id, name))
    if location == -1:
        return
    if isinstance(value, np.ndarray) and value.ndim == 2:
        gl.glUniformMatrix4fv(location, 1, gl.GL_TRUE, value.astype(np.float32))
    elif isinstance(value, np.ndarray):
        vector = value.astype(np.float32)
        (gl.glUniform1fv, gl.glUniform2fv, gl.glUniform3fv,
         gl.glUniform4fv)[len(vector) - 1](location, 1, vector)
    elif isinstance(value, (bool, int, np.integer)):
        gl.glUniform1i(location, int(value))
    else:
        gl.glUniform1f(location, float(value))


_LABEL_TARGET: dict = {}  # the process's label framebuffer: size, framebuffer, renderbuffers


def _label_target(width: int, height: int) -> int:
    """The single-sampled framebuffer of the label pass at (height, width):
    colour attachment 0 RGBA8 (segment colours), 1 and 2 float32 RGBA (normals, object
    coordinates) and a 24-bit depth buffer like pyrender's. One per process (in its one EGL
    context), made again when the size changes. (pyrender draws labels into its 4x multisampled
    framebuffer with multisampling off and copies them out: the same pixels, at more cost.)"""
    from OpenGL import GL as gl

    if _LABEL_TARGET.get("size") != (width, height):
        if _LABEL_TARGET:
            gl.glDeleteFramebuffers(1, [_LABEL_TARGET["framebuffer"]])
            gl.glDeleteRenderbuffers(4, _LABEL_TARGET["renderbuffers"])
        buffers = [int(b) for b in gl.glGenRenderbuffers(4)]
        framebuffer = int(gl.glGenFramebuffers(1))
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, framebuffer)
        formats = (gl.GL_RGBA8, gl.GL_RGBA32F, gl.GL_RGBA32F, gl.GL_DEPTH_COMPONENT24)
        attachments = (gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1, gl.GL_COLOR_ATTACHMENT2,
                       gl.GL_DEPTH_ATTACHMENT)
        for buffer, storage, attachment in zip(buffers, formats, attachments):
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, buffer)
            gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, storage, width, height)
            gl.glFramebufferRenderbuffer(gl.GL_DRAW_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER,
                                         buffer)
        _LABEL_TARGET.update(size=(width, height), framebuffer=framebuffer, renderbuffers=buffers)
    return _LABEL_TARGET["framebuffer"]


def _read_float_rgb(attachment: int, width: int, height: int) -> np.ndarray:
    """(H,W,3) float32 of a colour attachment of the bound read framebuffer, top row first."""
    from OpenGL import GL as gl

    gl.glReadBuffer(attachment)
    data = gl.glReadPixels(0, 0, width, height, gl.GL_RGB, gl.GL_FLOAT)
    return np.ascontiguousarray(np.frombuffer(data, np.float32).reshape(height, width, 3)[::-1])


def _begin_label_target(width: int, height: int, attachments: list[int]) -> None:
    """Draw into `attachments` of the label framebuffer, cleared (colour 0, depth 1), with the
    label pass's depth test and no multisampling."""
    from OpenGL import GL as gl

    gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, _label_target(width, height))
    gl.glDrawBuffers(len(attachments), attachments)
    gl.glViewport(0, 0, width, height)
    gl.glEnable(gl.GL_DEPTH_TEST)
    gl.glDepthMask(gl.GL_TRUE)
    gl.glDepthFunc(gl.GL_LESS)
    gl.glDepthRange(0.0, 1.0)
    gl.glDisable(gl.GL_MULTISAMPLE)
    gl.glClearColor(0.0, 0.0, 0.0, 0.0)
    gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)


# Sun i's shadow depth of the backdrop alone, drawn once per scene (within a scene neither the
# backdrop nor the sun's shadow camera moves): {"texture": GL id, "size": texels, "owner": the
# token of the SceneRenderer that drew it}.
_BACKDROP_DEPTH: dict[int, dict] = {}


def _backdrop_depth(index: int, size: int) -> dict:
    """The process's texture for sun `index`'s backdrop depth, (size, size), made in the shadow
    maps' own format (pyrender's unsized GL_DEPTH_COMPONENT), so one copies into the other."""
    from OpenGL import GL as gl

    cached = _BACKDROP_DEPTH.get(index)
    if cached is None or cached["size"] != size:
        if cached is not None:
            gl.glDeleteTextures(1, [cached["texture"]])
        texture = int(gl.glGenTextures(1))
        gl.glBindTexture(gl.GL_TEXTURE_2D, texture)
        gl.glTexImage2D(gl.GL_TEXTURE_2D, 0, gl.GL_DEPTH_COMPONENT, size, size, 0,
                        gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT, None)
        # One level without mipmaps: complete (so copyable) only with a non-mipmap filter.
        gl.glTexParameteri(gl.GL_TEXTURE_2D, gl.GL_TEXTURE_MIN_FILTER, gl.GL_NEAREST)
        gl.glBindTexture(gl.GL_TEXTURE_2D, 0)
        cached = _BACKDROP_DEPTH[index] = {"texture": texture, "size": size, "owner": None}
    return cached


def _copy_depth(source: int, target: int, size: int) -> None:
    """Copy a (size, size) depth texture into another of the same format (GL texture ids)."""
    from OpenGL import GL as gl

    gl.glCopyImageSubData(source, gl.GL_TEXTURE_2D, 0, 0, 0, 0, target, gl.GL_TEXTURE_2D, 0, 0, 0, 0,
                          size, size, 1)


def linear_depth(window_depth: np.ndarray, znear: float, zfar: float) -> np.ndarray:
    """z-depth (H,W) float32 from OpenGL window depths in [0,1] (1: nothing drawn -> 0), by
    pyrender's formula and float32 operations."""
    depth = 2.0 * window_depth - 1.0
    background = window_depth == 1.0
    depth[~background] = (2.0 * znear * zfar) / (zfar + znear - depth[~background] * (zfar - znear))
    depth[background] = 0.0
    return depth


def _offscreen_for(width: int, height: int, shadow_map_size: int):
    """The offscreen renderer, set to render (height, width) images with this shadow map size."""
    pyrender = _pyrender()
    # pyrender sizes new shadow maps and the shadow pass viewport from this module constant.
    pyrender.renderer.SHADOW_TEX_SZ = shadow_map_size
    pyrender.light.SHADOW_TEX_SZ = shadow_map_size
    offscreen = _offscreen()
    offscreen.viewport_width, offscreen.viewport_height = width, height
    return offscreen


def _frame_with_z(z_axis: np.ndarray) -> np.ndarray:
    """A 4x4 rotation whose +Z axis is `z_axis` (for lights, which shine along their -Z)."""
    z = z_axis / np.linalg.norm(z_axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    return geometry.make_pose(np.stack([x, np.cross(z, x), z], axis=-1), np.zeros(3))


def _textured_primitive(vertices: np.ndarray, faces: np.ndarray, uv: np.ndarray,
                        image: np.ndarray, roughness: float = 0.7):
    """A pyrender primitive with a repeating texture; per-vertex normals from the triangle mesh."""
    pyrender = _pyrender()
    normals = trimesh.Trimesh(vertices, faces, process=False).vertex_normals
    texture = pyrender.Texture(
        source=image, source_channels="RGB",
        sampler=pyrender.Sampler(wrapS=pyrender.GLTF.REPEAT, wrapT=pyrender.GLTF.REPEAT))
    material = pyrender.MetallicRoughnessMaterial(
        baseColorTexture=texture, metallicFactor=0.0, roughnessFactor=roughness)
    return pyrender.Primitive(positions=vertices.astype(np.float32),
                              normals=normals.astype(np.float32),
                              texcoord_0=uv.astype(np.float32), indices=faces.astype(np.int32),
                              material=material)


def object_mesh(asset: Asset, scale: float, texture_seed: int, uv_tiles: float,
                texture_size: int):
    """The render mesh of one object: its own texture, or a procedural one (box UVs if needed)."""
    vertices, faces, uv, image = asset.vertices * scale, asset.faces, asset.uv, asset.texture
    if image is None:
        image = textures.procedural_texture(np.random.default_rng(texture_seed), texture_size)
        if uv is None:
            vertices, faces, uv = textures.box_uv(asset.vertices, asset.faces, uv_tiles)
            vertices = vertices * scale
        else:
            uv = uv * uv_tiles
    return _pyrender().Mesh([_textured_primitive(vertices, faces, uv, image)])


def _grid_faces(rows: int, cols: int) -> np.ndarray:
    """Triangles of a (rows x cols) vertex grid, (2*(rows-1)*(cols-1), 3)."""
    idx = np.arange(rows * cols).reshape(rows, cols)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, :-1], idx[1:, 1:]
    return np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3),
                           np.stack([b, c, d], -1).reshape(-1, 3)])


def backdrop_mesh(radius: float, floor_tile: float, floor_image: np.ndarray,
                  dome_image: np.ndarray, equirect: bool, rings: int = 24, sectors: int = 96):
    """Floor disk (z = 0) and dome wall (half sphere) of `radius`: one pyrender mesh.

    One mesh, so its two parts are always drawn in the same order (pyrender orders meshes at
    equal distance by set iteration, which differs between processes; where floor and wall meet,
    the order would decide pixels).

    Procedural backdrop: the floor texture repeats every `floor_tile` units and the wall texture
    wraps around. `equirect`: both show one equirectangular image (lower half on the floor,
    nadir at the centre), as a Kubric HDRI dome does.
    """
    azimuth = np.linspace(0, 2 * np.pi, sectors + 1)  # (S,) last column repeats the first
    # Floor: rings of growing radius (fine near the centre, where the objects are).
    r = radius * np.linspace(0, 1, rings + 1) ** 1.5  # (R,)
    floor = np.stack([np.outer(r, np.cos(azimuth)), np.outer(r, np.sin(azimuth)),
                      np.zeros((rings + 1, sectors + 1))], -1)  # (R,S,3)
    # Wall: elevation from the horizon to the zenith.
    elevation = np.linspace(0, np.pi / 2, rings + 1)
    wall = radius * np.stack([np.outer(np.cos(elevation), np.cos(azimuth)),
                              np.outer(np.cos(elevation), np.sin(azimuth)),
                              np.outer(np.sin(elevation), np.ones(sectors + 1))], -1)  # (R,S,3)
    u = np.broadcast_to(azimuth / (2 * np.pi), (rings + 1, sectors + 1))
    if equirect:  # OpenGL texture v: 0 at the image's bottom row (nadir), 1 at its top (zenith)
        floor_uv = np.stack([u, np.broadcast_to(0.5 * (r / radius)[:, None], u.shape)], -1)
        wall_uv = np.stack([u, np.broadcast_to(0.5 + elevation[:, None] / np.pi, u.shape)], -1)
    else:
        floor_uv = floor[..., :2] / floor_tile
        wall_uv = np.stack([u * round(2 * np.pi * radius / (4 * floor_tile)),
                            wall[..., 2] / (4 * floor_tile)], -1)
    faces = _grid_faces(rings + 1, sectors + 1)
    return _pyrender().Mesh([
        _textured_primitive(floor.reshape(-1, 3), faces, floor_uv.reshape(-1, 2), floor_image, 0.9),
        _textured_primitive(wall.reshape(-1, 3), faces, wall_uv.reshape(-1, 2), dome_image, 1.0)])


class SceneRenderer:
    """A pyrender scene of one description; poses are set per render call."""

    def __init__(self, description: SceneDescription, object_indices: list[int],
                 assets: AssetLibrary, cfg):
        pyrender = _pyrender()
        self.height, self.width = description.height, description.width
        self.renderer = _offscreen_for(self.width, self.height, int(cfg.lights.shadow_map_size))
        self.scene = pyrender.Scene(ambient_light=np.full(3, description.ambient),
                                    bg_color=np.zeros(4))
        self.object_nodes = []
        self.boxes = {}  # node -> (box_min, box_scale) of the object coordinates (label pass)
        for index in object_indices:
            spec = description.objects[index]
            asset = assets.get(spec.asset_id)
            mesh = object_mesh(asset, spec.scale, spec.texture_seed, spec.uv_tiles,
                               int(cfg.assets.texture_size))
            self.object_nodes.append(self.scene.add(mesh))
            low, high = asset.bounds(spec.scale)
            self.boxes[self.object_nodes[-1]] = (low, 1.0 / np.maximum(high - low, 1e-12))
        # Backdrop: segment 0, never moves.
        rng = np.random.default_rng(description.backdrop_seed)
        if description.background_id is None:
            floor_image = textures.procedural_texture(rng, 2 * int(cfg.assets.texture_size))
            dome_image = textures.procedural_texture(rng, 2 * int(cfg.assets.texture_size))
            equirect = False
        else:
            floor_image = dome_image = assets.background(description.background_id)
            equirect = True
        self.backdrop = backdrop = self.scene.add(backdrop_mesh(
            float(cfg.backdrop.dome_radius), float(cfg.backdrop.floor_tile), floor_image,
            dome_image, equirect))
        # pyrender casts shadows from every directional light when asked to, so only the sun is
        # directional; the fill is a distant point light with the same irradiance at the origin.
        self.sun_nodes, self.point_nodes = [], []  # in the description's order
        for light in description.lights:
            if light.shadows:
                sun = _sun_light_class()(color=light.color, intensity=light.intensity)
                sun.half_width = float(cfg.lights.shadow_extent)
                self.sun_nodes.append(self.scene.add(sun, pose=_frame_with_z(-light.direction)))
            else:
                distance = float(cfg.backdrop.dome_radius) / 2
                node = pyrender.PointLight(color=light.color,
                                           intensity=light.intensity * distance**2)
                pose = geometry.make_pose(np.eye(3), -light.direction * distance)
                self.point_nodes.append(self.scene.add(node, pose=pose))
        self.shadows = bool(self.sun_nodes)
        self.light_counts = (len(self.sun_nodes), len(self.point_nodes))
        self._programs: dict = {}  # (primitive, flags, program flags) -> pyrender program
        self._uploaded: set[int] = set()  # render flags whose meshes and textures are uploaded
        self._token = object()  # marks the backdrop depths this renderer drew (_BACKDROP_DEPTH)
        for node in self.sun_nodes:  # pyrender puts the shadow camera at centroid - direction * scale
            pose = self.scene.get_pose(node)
            eye = self.scene.centroid + pose[:3, 2] * self.scene.scale
            node.light.focus_view = tuple((pose[:3, :3].T @ -eye)[:2])
        # Each sun's shadow camera (V, P), placed once for the scene as focus_view assumes.
        # pyrender would place it again at every frame from the bounds of all meshes, which the
        # objects' rotated boxes change, shifting the map by fractions of a texel each frame.
        shadow_flags = pyrender.RenderFlags.OFFSCREEN | pyrender.RenderFlags.SHADOWS_DIRECTIONAL
        self.shadow_cameras = [self.renderer._renderer._get_light_cam_matrices(
            self.scene, node, shadow_flags) for node in self.sun_nodes]
        K = geometry.intrinsics_from_lens(description.camera.focal_mm,
                                          description.camera.sensor_mm, self.height, self.width)
        camera = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5,
                                           znear=float(cfg.camera.znear),
                                           zfar=float(cfg.camera.zfar))
        self.camera_node = self.scene.add(camera)
        self.boxes[backdrop] = (np.zeros(3), np.zeros(3))  # object coordinates 0
        # Segment k (1-based) encoded as colour (k mod 256, k div 256, 0).
        self.seg_colors = {backdrop: np.zeros(3)}
        self.seg_colors.update({node: np.array([k % 256, k // 256, 0])
                                for k, node in enumerate(self.object_nodes, start=1)})

    def _set_poses(self, object_to_world: np.ndarray, cam_to_world: np.ndarray) -> None:
        """Pose the objects (K,4,4) and the camera (4,4, OpenCV) for one render, and keep every
        mesh node's world pose (pyrender's get_pose walks the scene graph on each call) and
        pyrender's draw order (`_sorted_mesh_nodes`: the opaque meshes from the farthest to the
        nearest, node origin to camera; the same set order and the same keys, so the same order)."""
        for node, pose in zip(self.object_nodes, object_to_world):
            self.scene.set_pose(node, pose)
        self.scene.set_pose(self.camera_node, cam_to_world @ OPENCV_TO_OPENGL)
        self.world = {node: self.scene.get_pose(node) for node in self.scene.mesh_nodes}
        camera = self.scene.get_pose(self.camera_node)[:3, 3]
        self.draw_order = sorted(
            self.world, key=lambda node: -np.linalg.norm(self.world[node][:3, 3] - camera))

    # The three passes draw pyrender's uploaded meshes with pyrender's programs, framebuffers
    # and shadow maps, in pyrender's draw order and GL state, but set each pass's per-frame
    # uniforms (cameras, lights) once per program instead of once per primitive, and keep every
    # uniform location and program: pyrender's own loop costs more CPU than llvmpipe's drawing.

    def _begin(self, flags: int):
        """The GL context made current at this scene's size, meshes and textures uploaded;
        returns pyrender's renderer."""
        offscreen = self.renderer
        offscreen._platform.make_current()
        renderer = offscreen._renderer
        renderer.viewport_width, renderer.viewport_height = self.width, self.height
        renderer._program_cache.light_counts = self.light_counts
        if flags not in self._uploaded:  # the meshes never change: upload once per kind of pass
            renderer._update_context(self.scene, flags)
            self._uploaded.add(flags)
        return renderer

    def _program(self, renderer, primitive, flags: int, program_flags: int):
        """pyrender's program for `primitive` in a pass, bound; kept per scene."""
        key = (id(primitive), flags, program_flags)
        program = self._programs.get(key)
        if program is None:
            program = self._programs[key] = renderer._get_primitive_program(
                primitive, flags, program_flags)
        program._bind()
        return program

    def _draw(self, primitive) -> None:
        """One primitive, its buffers bound and unbound (pyrender's instanced draw call)."""
        import ctypes

        from OpenGL import GL as gl

        primitive._bind()
        instances = 1 if primitive.poses is None else len(primitive.poses)
        gl.glDrawElementsInstanced(primitive.mode, primitive.indices.size, gl.GL_UNSIGNED_INT,
                                   ctypes.c_void_p(0), instances)
        primitive._unbind()

    def _opaque_state(self) -> None:
        """Every pass's state: filled triangles, back faces culled (every pass draws the same
        triangles, so the lit image shows the surfaces the labels describe), blending off
        (pyrender's replace-blending, ONE/ZERO, writes the same bits and costs llvmpipe a read
        of every covered sample)."""
        from OpenGL import GL as gl

        gl.glDisable(gl.GL_BLEND)
        gl.glPolygonMode(gl.GL_FRONT_AND_BACK, gl.GL_FILL)
        gl.glDisable(gl.GL_PROGRAM_POINT_SIZE)
        gl.glEnable(gl.GL_CULL_FACE)
        gl.glCullFace(gl.GL_BACK)

    def _pass(self, renderer, nodes, flags: int, program_flags: int, V, P, per_program=None,
              per_primitive=None) -> None:
        """Every primitive of `nodes` in their order: V, P, cam_pos and per_program(program) once
        per program, then per_primitive(program, node, primitive) and the model matrix M."""
        cam_pos = self.scene.get_pose(self.scene.main_camera_node)[:3, 3]
        framed = set()
        program = None
        for node in nodes:
            pose = self.world[node]
            for primitive in node.mesh.primitives:
                program = self._program(renderer, primitive, flags, program_flags)
                if program._program_id not in framed:
                    framed.add(program._program_id)
                    _set_uniform(program, "V", V)
                    _set_uniform(program, "P", P)
                    _set_uniform(program, "cam_pos", cam_pos)
                    if per_program is not None:
                        per_program(program)
                if per_primitive is not None:
                    per_primitive(program, node, primitive)
                _set_uniform(program, "M", pose)
                self._draw(primitive)
        if program is not None:
            program._unbind()

    def _bind_lights(self, program, shadow_unit: int | None, light_matrices: list) -> None:
        """The lit pass's light uniforms: the sun(s) (directional, their shadow maps on
        texture units from `shadow_unit`, shadow clip from world (4,4) each in
        `light_matrices`) and the point lights, in the description's order."""
        from OpenGL import GL as gl

        scene = self.scene
        _set_uniform(program, "ambient_light", scene.ambient_light)
        for i, node in enumerate(self.sun_nodes):
            name = f"directional_lights[{i}]."
            _set_uniform(program, name + "direction", -scene.get_pose(node)[:3, 2])
            _set_uniform(program, name + "color", node.light.color)
            _set_uniform(program, name + "intensity", node.light.intensity)
            if shadow_unit is not None:
                gl.glActiveTexture(gl.GL_TEXTURE0 + shadow_unit + i)
                node.light.shadow_texture._bind()
                _set_uniform(program, name + "shadow_map", shadow_unit + i)
                _set_uniform(program, name + "light_matrix", light_matrices[i])
        for i, node in enumerate(self.point_nodes):
            name = f"point_lights[{i}]."
            _set_uniform(program, name + "position", scene.get_pose(node)[:3, 3])
            _set_uniform(program, name + "color", node.light.color)
            _set_uniform(program, name + "intensity", node.light.intensity)

    def _shadow_map(self, renderer, nodes, index: int, flags: int) -> np.ndarray:
        """Draw sun `index`'s shadow map; returns its shadow clip from world matrix (4,4).

        A depth map holds each texel's nearest depth whatever the drawing order, so the
        backdrop's depth (neither it nor the sun's shadow camera moves) is drawn once per
        scene, kept, and copied into the map before the objects are drawn: the same bits as
        drawing everything, without rasterising the floor over the whole map at every frame.
        """
        node = self.sun_nodes[index]
        shadow = node.light.shadow_texture
        renderer._configure_shadow_mapping_viewport(node.light, flags)  # bound and cleared
        V, P = self.shadow_cameras[index]
        self._opaque_state()
        program_flags = _pyrender().constants.ProgramFlags.NONE
        backdrop = _backdrop_depth(index, shadow.width)
        if backdrop["owner"] is self._token:
            _copy_depth(backdrop["texture"], shadow._texid, shadow.width)
        else:
            self._pass(renderer, [self.backdrop], flags, program_flags, V, P)
            _copy_depth(shadow._texid, backdrop["texture"], shadow.width)
            backdrop["owner"] = self._token
        self._pass(renderer, [n for n in nodes if n is not self.backdrop], flags, program_flags,
                   V, P)
        return P.dot(V)

    def render_rgb(self, object_to_world: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
        """uint8 (H,W,3) lit image. object_to_world (K,4,4), cam_to_world (4,4) OpenCV."""
        from OpenGL import GL as gl

        pyrender = _pyrender()
        RenderFlags, ProgramFlags = pyrender.RenderFlags, pyrender.constants.ProgramFlags
        self._set_poses(object_to_world, cam_to_world)
        flags = RenderFlags.OFFSCREEN | (RenderFlags.SHADOWS_DIRECTIONAL if self.shadows else 0)
        renderer = self._begin(flags)
        scene = self.scene
        nodes = self.draw_order
        light_matrices = []
        if self.shadows:  # shadow maps: depth from each sun's orthographic camera
            for index in range(len(self.sun_nodes)):
                light_matrices.append(self._shadow_map(renderer, nodes, index, flags))
        renderer._configure_forward_pass_viewport(flags)
        gl.glClearColor(*scene.bg_color)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        gl.glEnable(gl.GL_MULTISAMPLE)
        shadow_unit = 0 if self.shadows else None  # texture units: shadow maps, then material
        material_unit = len(self.sun_nodes) if self.shadows else 0

        def per_program(program):
            self._bind_lights(program, shadow_unit, light_matrices)
            _set_uniform(program, "material.base_color_texture", material_unit)

        def material(program, node, primitive):
            material = primitive.material
            gl.glActiveTexture(gl.GL_TEXTURE0 + material_unit)
            material.baseColorTexture._bind()
            _set_uniform(program, "material.base_color_factor", material.baseColorFactor)
            _set_uniform(program, "material.roughness_factor", material.roughnessFactor)

        self._opaque_state()
        V, P = renderer._get_camera_matrices(scene)
        self._pass(renderer, nodes, flags, ProgramFlags.USE_MATERIAL, V, P, per_program, material)
        width, height = renderer._main_fb_dims
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, renderer._main_fb_ms)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, renderer._main_fb)
        gl.glBlitFramebuffer(0, 0, width, height, 0, 0, width, height, gl.GL_COLOR_BUFFER_BIT,
                             gl.GL_LINEAR)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, renderer._main_fb)
        data = gl.glReadPixels(0, 0, width, height, gl.GL_RGB, gl.GL_UNSIGNED_BYTE)
        color = np.frombuffer(data, np.uint8).reshape(height, width, 3)
        return np.ascontiguousarray(color[::-1])  # OpenGL's rows run bottom-up

    def render_labels(self, object_to_world: np.ndarray, cam_to_world: np.ndarray,
                      surface: bool = False):
        """(depth, segmentation, normal, coordinates) at the pixel centres: z-depth float32 (H,W),
        segmentation int32 (H,W) and, with `surface`, world-space unit shading normals float32
        (H,W,3) and object coordinates float32 (H,W,3) in [0,1]^3 (0 on the backdrop), else None
        and None.

        One pass either way. Without `surface` it draws with pyrender's segmentation program;
        with it, with datagen's surface program (shaders/surface.*), which computes the clip
        position by the segmentation program's expression and writes the same segment colour,
        so depth and segmentation are the same bits, and the normals and coordinates cover
        exactly their pixels. object_to_world (K,4,4), cam_to_world (4,4) OpenCV.
        """
        from OpenGL import GL as gl

        pyrender = _pyrender()
        self._set_poses(object_to_world, cam_to_world)
        renderer = self._begin(pyrender.RenderFlags.SEG)
        outputs = [gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1, gl.GL_COLOR_ATTACHMENT2]
        _begin_label_target(self.width, self.height, outputs if surface else outputs[:1])
        V, P = renderer._get_camera_matrices(self.scene)

        def segment_and_box(program, node, primitive):
            _set_uniform(program, "color", self.seg_colors[node] / 255.0)
            if surface:
                low, scale = self.boxes[node]
                _set_uniform(program, "box_min", low)
                _set_uniform(program, "box_scale", scale)

        self._opaque_state()
        if surface:  # pyrender's FLAT program, served by shaders/surface.* (DatagenShaders)
            flags, program_flags = pyrender.RenderFlags.FLAT, pyrender.constants.ProgramFlags.NONE
        else:
            flags, program_flags = (pyrender.RenderFlags.SEG,
                                    pyrender.constants.ProgramFlags.USE_MATERIAL)
        self._pass(renderer, self.draw_order, flags, program_flags, V, P,
                   per_primitive=segment_and_box)
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, _label_target(self.width, self.height))
        gl.glReadBuffer(gl.GL_COLOR_ATTACHMENT0)
        data = gl.glReadPixels(0, 0, self.width, self.height, gl.GL_RGB, gl.GL_UNSIGNED_BYTE)
        colour = np.frombuffer(data, np.uint8).reshape(self.height, self.width, 3)[::-1]
        segmentation = colour[..., 0].astype(np.int32) + 256 * colour[..., 1].astype(np.int32)
        data = gl.glReadPixels(0, 0, self.width, self.height, gl.GL_DEPTH_COMPONENT, gl.GL_FLOAT)
        window = np.frombuffer(data, np.float32).reshape(self.height, self.width)[::-1]
        camera = self.scene.main_camera_node.camera
        depth = linear_depth(window, camera.znear, camera.zfar)
        if not surface:
            return depth, segmentation, None, None
        normal, coordinates = (_read_float_rgb(attachment, self.width, self.height)
                               for attachment in outputs[1:])
        return depth, segmentation, normal, coordinates


def shutter_times(frame: int, shutter: float, num_samples: int) -> np.ndarray:
    """Sub-frame times (num_samples,) spread evenly over a shutter of `shutter` frames at `frame`.

    The shutter is centred on the frame time, where the labels are.
    """
    return frame + shutter * ((np.arange(num_samples) + 0.5) / num_samples - 0.5)


def num_blur_samples(shutter: float, cfg) -> int:
    """Sub-frame renders per frame for a shutter open `shutter` frames (1 = sharp)."""
    if shutter <= 0:
        return 1
    wanted = int(np.ceil(shutter * cfg.blur.samples_per_frame))
    return int(np.clip(wanted, 2, cfg.blur.max_samples))


def render_blurred(renderer: SceneRenderer, object_poses, camera_poses, times: np.ndarray):
    """Mean of sub-frame renders, rounded to uint8 (H,W,3).

    object_poses(times) -> (K,n,4,4) and camera_poses(times) -> (n,4,4) give the poses.
    """
    objects, cameras = object_poses(times), camera_poses(times)  # (K,n,4,4), (n,4,4)
    total = np.zeros((renderer.height, renderer.width, 3))
    for i in range(len(times)):
        total += renderer.render_rgb(objects[:, i], cameras[i])
    return np.round(total / len(times)).astype(np.uint8)
