"""The moderngl/EGL G-buffer against the NumPy reference rasterizer the procedural scenes were rendered
with, the pixel convention of the projection, culling, normals and the no-GL fallback."""

import numpy as np
import pytest
import torch
import trimesh

from omnirecon.cameras import Cameras
from omnirecon.data import load_scene
from omnirecon.data.synth.generate import SynthOptions, generate_scene
from omnirecon.errors import InputError
from omnirecon.render import raster
from omnirecon.render.raster import MeshRasterizer, projection_matrix

needs_gl = pytest.mark.usefixtures("gl")  # skips without EGL, fails under CI=true (conftest)


@pytest.fixture(scope="module")
def scene(tmp_path_factory):
    folder = generate_scene(tmp_path_factory.mktemp("raster"), 11, SynthOptions(resolution=64, views=8))
    return load_scene(folder)


def scene_mesh(scene) -> trimesh.Trimesh:
    mesh = trimesh.load(scene.mesh_path, process=False, force="mesh")
    T = scene.mesh_to_scene.double().numpy()
    return trimesh.Trimesh(np.asarray(mesh.vertices) @ T[:3, :3].T + T[:3, 3], np.asarray(mesh.faces), process=False)


def test_projection_matrix_maps_pixels_to_window_coordinates():
    fx, fy, cx, cy, W, H, near, far = 50.0, 60.0, 31.0, 22.5, 64, 48, 0.5, 8.0
    P = projection_matrix(fx, fy, cx, cy, W, H, near, far)
    for x, y, z in [(0.3, -0.2, 2.0), (-1.0, 0.7, 5.0)]:
        clip = P @ np.array([x, y, z, 1.0])
        assert clip[3] == pytest.approx(z)  # w_clip = camera z
        ndc = clip[:3] / clip[3]
        u, v = fx * x / z + cx, fy * y / z + cy
        # viewport (0, 0, W, H): window = (ndc + 1) / 2 * size equals the pixel coordinates (y down, no flip)
        assert (ndc[0] + 1) / 2 * W == pytest.approx(u) and (ndc[1] + 1) / 2 * H == pytest.approx(v)
    assert (P @ [0, 0, near, 1])[2] / near == pytest.approx(-1) and (P @ [0, 0, far, 1])[2] / far == pytest.approx(1)


@needs_gl
def test_gbuffer_matches_reference_rasterizer(scene):
    mesh = scene_mesh(scene)
    gl = MeshRasterizer.from_trimesh(mesh, backend="gl")
    ref = MeshRasterizer.from_trimesh(mesh, backend="reference")
    assert gl.backend == "gl" and ref.backend == "reference"
    scale = float((scene.bounds[1] - scene.bounds[0]).norm())
    for i in range(len(scene)):
        cam = scene.cameras[i]
        a, b = gl.rasterize(cam, normals="vertex"), ref.rasterize(cam, normals="vertex")
        covered = a.mask | b.mask
        assert (a.face == b.face)[covered].float().mean() >= 0.99, i
        assert (a.mask != b.mask).float().mean() <= 0.005  # same coverage (pixel-centre sampling)
        gt = scene.depths[i] > 0  # the generator's own depth maps: same silhouettes
        assert (a.mask != gt).float().mean() <= 0.005
        both = a.mask & b.mask
        same = both & (a.face == b.face)
        assert ((a.depth - b.depth)[same].abs() <= 1e-3 * scale).all()
        assert ((a.points - b.points)[same].abs() <= 1e-3 * scale).all()
        close = (a.depth - b.depth).abs() <= 1e-3 * scale  # elsewhere: a silhouette pixel may pick another object
        assert close[both].float().mean() >= 0.995
        for g in (a, b):
            assert torch.allclose(g.bary.sum(-1)[g.mask], torch.ones(int(g.mask.sum())), atol=1e-5)
            assert (g.bary[g.mask] >= -1e-5).all() and (g.depth[~g.mask] == 0).all() and (g.face[~g.mask] == -1).all()
            assert torch.allclose(g.normals[g.mask].norm(dim=-1), torch.ones(int(g.mask.sum())), atol=1e-4)


@needs_gl
def test_points_depth_and_barycentrics_are_consistent_with_the_camera(scene):
    """Surface points project back to their pixel centres at their z-depth; bary interpolates them."""
    mesh = scene_mesh(scene)
    with MeshRasterizer.from_trimesh(mesh, backend="gl") as gl:
        cam = scene.cameras[3].rescaled(2)  # another size: a second framebuffer in the same context
        g = gl.rasterize(cam, normals="face")
        hit = g.mask
        proj = cam.project(g.points[hit].double())
        centres = cam.pixel_centers()[hit]
        assert (proj.uv[0] - centres).abs().max() < 2e-2
        assert torch.allclose(proj.depth[0].float(), g.depth[hit], rtol=1e-4)
        v = torch.from_numpy(np.asarray(mesh.vertices)).float()[torch.from_numpy(np.asarray(mesh.faces))[g.face[hit]]]
        assert torch.allclose((g.bary[hit][:, :, None] * v).sum(1), g.points[hit], atol=1e-4)
        # culled render: every visible face looks towards the camera
        rays = g.points[hit] - cam.centers[0].float()
        assert ((g.normals[hit] * rays).sum(-1) < 0).all()
        surf = gl.surface(cam)  # the compact pass agrees with the full G-buffer
        assert torch.equal(surf.pixels, hit.reshape(-1).nonzero()[:, 0])
        assert torch.allclose(surf.points, g.points[hit], atol=1e-6) and torch.allclose(surf.depth, g.depth[hit])
        assert surf.image(surf.depth[:, None], 0.0)[..., 0].equal(g.depth)


@needs_gl
def test_two_sided_rasterization_matches_reference(scene):
    mesh = scene_mesh(scene)
    cam = scene.cameras[5]
    a = MeshRasterizer.from_trimesh(mesh, backend="gl", cull_back_faces=False).rasterize(cam)
    b = MeshRasterizer.from_trimesh(mesh, backend="reference", cull_back_faces=False).rasterize(cam)
    covered = a.mask | b.mask
    assert (a.face == b.face)[covered].float().mean() >= 0.99
    assert torch.allclose(a.bary[a.mask & b.mask].sum(-1), torch.ones(int((a.mask & b.mask).sum())), atol=1e-5)
    # a single triangle seen from behind: culled by default, drawn two-sided
    tri = (np.array([[0, 0, 3.0], [1, 0, 3], [0, 1, 3]]), np.array([[0, 1, 2]]))  # normal +z: a back face
    f = torch.tensor([40.0])
    cam = Cameras(f, f, f * 0 + 16, f * 0 + 16, torch.eye(4, dtype=torch.float64)[None], 32, 32)
    for backend in ("gl", "reference"):
        assert not MeshRasterizer(*tri, backend=backend).rasterize(cam).mask.any()
        two = MeshRasterizer(*tri, backend=backend, cull_back_faces=False).rasterize(cam)
        assert two.mask.any() and torch.allclose(two.depth[two.mask], torch.full((int(two.mask.sum()),), 3.0))


def test_gl_backend_unavailable_gives_one_line_error(monkeypatch):
    monkeypatch.setattr(raster, "gl_unavailable_reason", lambda: "no headless EGL context (test)")
    tri = (np.array([[0, 0, 3.0], [0, 1, 3], [1, 0, 3]]), np.array([[0, 1, 2]]))  # normal -z: faces the camera
    with pytest.raises(InputError) as err:
        MeshRasterizer(*tri, backend="gl")
    assert "\n" not in str(err.value) and "EGL" in str(err.value) and "reference" in str(err.value)
    auto = MeshRasterizer(*tri, backend="auto")
    assert auto.backend == "reference"
    f = torch.tensor([40.0])
    cam = Cameras(f, f, f * 0 + 16, f * 0 + 16, torch.eye(4, dtype=torch.float64)[None], 32, 32)
    g = auto.rasterize(cam)
    assert g.mask.any() and torch.allclose(g.depth[g.mask], torch.full((int(g.mask.sum()),), 3.0))
    surf = auto.surface(cam)
    assert torch.equal(surf.pixels, g.mask.reshape(-1).nonzero()[:, 0]) and torch.equal(surf.points, g.points[g.mask])
    with pytest.raises(InputError, match="vertices that do not exist"):
        MeshRasterizer(tri[0], np.array([[0, 1, 5]]), backend="reference")


@needs_gl
def test_two_rasterizers_each_draw_their_own_mesh(scene):
    """Each rasterizer makes its own GL context current: with two alive, the older one must not draw
    the newer one's mesh (it did before the fix)."""
    mesh = scene_mesh(scene)
    half = trimesh.Trimesh(mesh.vertices, mesh.faces[: len(mesh.faces) // 2], process=False)
    cam = scene.cameras[0]
    with MeshRasterizer.from_trimesh(mesh, backend="gl") as a:
        full_alone = a.rasterize(cam, normals="none").face.clone()
        with MeshRasterizer.from_trimesh(half, backend="gl") as b:
            half_b = b.rasterize(cam, normals="none").face
            full_a = a.rasterize(cam, normals="none").face  # after b was created and used
            assert torch.equal(full_a, full_alone)
            assert (half_b >= 0).sum() < (full_a >= 0).sum()


@needs_gl
def test_depth_pass_equals_the_gbuffer_depth(scene):
    """The depth-only pass (the mesh renderer's frame path) draws the G-buffer's z-depth; its reference
    twin is the reference rasterizer's depth."""
    mesh = scene_mesh(scene)
    gl = MeshRasterizer.from_trimesh(mesh, backend="gl")
    ref = MeshRasterizer.from_trimesh(mesh, backend="reference")
    for i in range(3):
        cam = scene.cameras[i]
        d = gl.depth(cam).clone()
        g = gl.rasterize(cam, normals="none")
        assert d.shape == (cam.height, cam.width) and torch.equal(d > 0, g.mask)
        assert torch.allclose(d, g.depth, rtol=1e-6, atol=0)
        assert torch.equal(ref.depth(cam), ref.rasterize(cam, normals="none").depth)
        # drawn ahead (read back after another pass in the context) and on the reference backend: the same depths
        ahead, ahead_ref = gl.depth_ahead(cam), ref.depth_ahead(cam)
        gl.rasterize(scene.cameras[(i + 1) % 3].rescaled(0.5), normals="none")
        assert torch.equal(ahead(), d) and torch.equal(ahead_ref(), ref.depth(cam))
    # the face pass (gl_PrimitiveID of the indexed mesh) gives the G-buffer's triangle ids, culled and two-sided
    for cull in (True, False):
        with MeshRasterizer.from_trimesh(mesh, backend="gl", cull_back_faces=cull) as r:
            for i in range(3):
                f = r.face_ids(scene.cameras[i].rescaled(2))
                assert (f >= 0).any() and np.array_equal(f, r.rasterize(scene.cameras[i].rescaled(2)).face.numpy())
        assert np.array_equal(MeshRasterizer.from_trimesh(mesh, backend="reference").face_ids(scene.cameras[0]),
                              ref.rasterize(scene.cameras[0]).face.numpy())
    # the depth and surface passes draw shared vertices by index: the same pixels as the same triangles unshared
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    with MeshRasterizer(v[f].reshape(-1, 3), np.arange(3 * len(f)).reshape(-1, 3), backend="gl") as soup:
        cam = scene.cameras[1]
        assert torch.equal(gl.depth(cam), soup.depth(cam))
        a, b = gl.surface(cam), soup.surface(cam)
        assert len(a.pixels) > 0 and torch.equal(a.pixels, b.pixels) and torch.equal(a.points, b.points)
        assert torch.equal(a.depth, b.depth)


def test_reference_rasterizer_result_does_not_depend_on_its_candidate_runs():
    """The NumPy z-buffer expands triangles' bounding boxes a run at a time (its memory bound): any run size, down
    to one triangle per run, gives the same buffer, exact depth ties (duplicated triangles) included."""
    from omnirecon.render.zbuffer import rasterize

    rng = np.random.default_rng(0)
    K = np.array([[80.0, 0, 40], [0, 80, 30], [0, 0, 1]])
    V = np.concatenate([rng.uniform([-2, -2, 3], [2, 2, 6], (200, 3)), [[-5, -5, 4], [5, -5, 4], [0, 5, 4]]])
    F = rng.integers(0, 200, (150, 3))
    F = np.concatenate([F, F[:20], [[200, 201, 202], [200, 201, 202], [202, 201, 200]]])  # ties and a big one
    whole = rasterize(V, F, K, np.eye(4), 80, 60)
    assert (whole.face >= 150).any()  # the duplicates and the big triangle are drawn somewhere
    for run in (1, 13, 500):
        part = rasterize(V, F, K, np.eye(4), 80, 60, max_candidates=run)
        assert np.array_equal(part.face, whole.face) and np.array_equal(part.depth, whole.depth)
        assert np.array_equal(part.bary, whole.bary)
