"""Rendering with pyrender on EGL (Mesa's software renderer works): RGB, z-depth, segmentation,
surface normals and object coordinates.

- RGB: lit by a shadow-casting sun, a fill light and ambient light, 4x multisampled, with
  datagen's own lit-pass shaders (datagen/shaders/: textured Lambert + Blinn-Phong, 4-tap shadow
  filter), several times cheaper than pyrender's PBR shader on a software renderer.
- Labels: z-depth and instance segmentation from pyrender's segmentation pass, which renders
  without multisampling, so every pixel holds the surface hit by the ray through its centre.
- Surface (optional layers): one more pass like the label pass (same pixels, same culling) with
  datagen's surface shaders writing the world-space shading normal and the object coordinates
  into two float32 attachments of the process's own framebuffer.
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
        def get_program(self, vertex_shader, fragment_shader, geometry_shader=None,
                        defines=None):
            if fragment_shader == "mesh.frag":  # the lit pass; depth, shadow and seg stay
                vertex_shader = str(SHADER_DIR / "mesh.vert")
                fragment_shader = str(SHADER_DIR / "mesh.frag")
            elif fragment_shader == "flat.frag":  # pyrender's FLAT pass, unused: the surface pass
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


_SURFACE_TARGET: dict = {}  # the process's surface framebuffer: size, framebuffer, renderbuffers


def _surface_target(width: int, height: int) -> int:
    """The framebuffer of the surface pass at (height, width): two float32 RGBA colour
    attachments (normal, object coordinates) and a 24-bit depth buffer like pyrender's. One per
    process (in its one EGL context), made again when the size changes."""
    from OpenGL import GL as gl

    if _SURFACE_TARGET.get("size") != (width, height):
        if _SURFACE_TARGET:
            gl.glDeleteFramebuffers(1, [_SURFACE_TARGET["framebuffer"]])
            gl.glDeleteRenderbuffers(3, _SURFACE_TARGET["renderbuffers"])
        buffers = [int(b) for b in gl.glGenRenderbuffers(3)]
        framebuffer = int(gl.glGenFramebuffers(1))
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, framebuffer)
        formats = (gl.GL_RGBA32F, gl.GL_RGBA32F, gl.GL_DEPTH_COMPONENT24)
        attachments = (gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1, gl.GL_DEPTH_ATTACHMENT)
        for buffer, storage, attachment in zip(buffers, formats, attachments):
            gl.glBindRenderbuffer(gl.GL_RENDERBUFFER, buffer)
            gl.glRenderbufferStorage(gl.GL_RENDERBUFFER, storage, width, height)
            gl.glFramebufferRenderbuffer(gl.GL_DRAW_FRAMEBUFFER, attachment, gl.GL_RENDERBUFFER,
                                         buffer)
        _SURFACE_TARGET.update(size=(width, height), framebuffer=framebuffer, renderbuffers=buffers)
    return _SURFACE_TARGET["framebuffer"]


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
        baseColorTexture=texture, metallicFactor=0.0, roughnessFactor=roughness, doubleSided=True)
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
        self.boxes = {}  # node -> (box_min, box_scale) of the surface pass (object coordinates)
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
        backdrop = self.scene.add(backdrop_mesh(
            float(cfg.backdrop.dome_radius), float(cfg.backdrop.floor_tile), floor_image,
            dome_image, equirect))
        # pyrender casts shadows from every directional light when asked to, so only the sun is
        # directional; the fill is a distant point light with the same irradiance at the origin.
        self.shadows = False
        suns = []
        for light in description.lights:
            if light.shadows:
                sun = _sun_light_class()(color=light.color, intensity=light.intensity)
                sun.half_width = float(cfg.lights.shadow_extent)
                suns.append(self.scene.add(sun, pose=_frame_with_z(-light.direction)))
                self.shadows = True
            else:
                distance = float(cfg.backdrop.dome_radius) / 2
                node = pyrender.PointLight(color=light.color,
                                           intensity=light.intensity * distance**2)
                pose = geometry.make_pose(np.eye(3), -light.direction * distance)
                self.scene.add(node, pose=pose)
        for node in suns:  # pyrender puts the shadow camera at centroid - direction * scale
            pose = self.scene.get_pose(node)
            eye = self.scene.centroid + pose[:3, 2] * self.scene.scale
            node.light.focus_view = tuple((pose[:3, :3].T @ -eye)[:2])
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
        for node, pose in zip(self.object_nodes, object_to_world):
            self.scene.set_pose(node, pose)
        self.scene.set_pose(self.camera_node, cam_to_world @ OPENCV_TO_OPENGL)

    def render_rgb(self, object_to_world: np.ndarray, cam_to_world: np.ndarray) -> np.ndarray:
        """uint8 (H,W,3) lit image. object_to_world (K,4,4), cam_to_world (4,4) OpenCV."""
        pyrender = _pyrender()
        self._set_poses(object_to_world, cam_to_world)
        flags = pyrender.RenderFlags.SHADOWS_DIRECTIONAL if self.shadows else 0
        color, _ = self.renderer.render(self.scene, flags=flags)
        return np.ascontiguousarray(color[..., :3])

    def render_labels(self, object_to_world: np.ndarray, cam_to_world: np.ndarray):
        """z-depth float32 (H,W) and segmentation int32 (H,W) at the pixel centres."""
        pyrender = _pyrender()
        self._set_poses(object_to_world, cam_to_world)
        color, depth = self.renderer.render(self.scene, flags=pyrender.RenderFlags.SEG,
                                            seg_node_map=self.seg_colors)
        segmentation = color[..., 0].astype(np.int32) + 256 * color[..., 1].astype(np.int32)
        return depth.astype(np.float32), segmentation

    def render_surface(self, object_to_world: np.ndarray,
                       cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """World-space unit shading normals float32 (H,W,3) and object coordinates float32
        (H,W,3) in [0,1]^3 (0 on the backdrop) at the pixel centres, covering exactly the pixels
        of `render_labels` (same clip positions, depth test, culling and draw order).

        object_to_world (K,4,4), cam_to_world (4,4) OpenCV.
        """
        from OpenGL import GL as gl

        pyrender = _pyrender()
        self._set_poses(object_to_world, cam_to_world)
        offscreen = self.renderer
        offscreen._platform.make_current()
        renderer = offscreen._renderer
        flags = pyrender.RenderFlags.SEG  # pyrender's label-pass state: no material, back faces culled
        renderer._update_context(self.scene, flags)
        gl.glBindFramebuffer(gl.GL_DRAW_FRAMEBUFFER, _surface_target(self.width, self.height))
        gl.glDrawBuffers(2, [gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1])
        gl.glViewport(0, 0, self.width, self.height)
        gl.glEnable(gl.GL_DEPTH_TEST)
        gl.glDepthMask(gl.GL_TRUE)
        gl.glDepthFunc(gl.GL_LESS)
        gl.glDepthRange(0.0, 1.0)
        gl.glDisable(gl.GL_MULTISAMPLE)
        gl.glClearColor(0.0, 0.0, 0.0, 0.0)
        gl.glClear(gl.GL_COLOR_BUFFER_BIT | gl.GL_DEPTH_BUFFER_BIT)
        V, P = renderer._get_camera_matrices(self.scene)
        program = None
        for node in renderer._sorted_mesh_nodes(self.scene):
            low, scale = self.boxes[node]
            for primitive in node.mesh.primitives:
                program = renderer._get_primitive_program(primitive, pyrender.RenderFlags.FLAT,
                                                          pyrender.constants.ProgramFlags.NONE)
                program._bind()
                program.set_uniform("V", V)
                program.set_uniform("P", P)
                program.set_uniform("box_min", low)
                program.set_uniform("box_scale", scale)
                renderer._bind_and_draw_primitive(primitive, self.scene.get_pose(node), program,
                                                  flags)
        if program is not None:
            program._unbind()
        gl.glBindFramebuffer(gl.GL_READ_FRAMEBUFFER, _surface_target(self.width, self.height))
        images = []
        for attachment in (gl.GL_COLOR_ATTACHMENT0, gl.GL_COLOR_ATTACHMENT1):
            gl.glReadBuffer(attachment)
            data = gl.glReadPixels(0, 0, self.width, self.height, gl.GL_RGB, gl.GL_FLOAT)
            image = np.frombuffer(data, np.float32).reshape(self.height, self.width, 3)
            images.append(np.ascontiguousarray(image[::-1]))  # OpenGL's rows run bottom-up
        return images[0], images[1]


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
