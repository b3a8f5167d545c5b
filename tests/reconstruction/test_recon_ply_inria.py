"""``splat.ply`` in the exact layout of the Inria 3DGS code, read as its ``load_ply`` and the SIBR viewer read it."""

import numpy as np
import pytest
import torch
from plyfile import PlyData

from tacsplat.errors import SceneFormatError
from tacsplat.reconstruction.gaussians import Gaussians, num_sh_bases
from tacsplat.reconstruction.ply import load_ply, save_ply, touch_sidecar_path

INRIA_NAMES = (
    ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    + [f"f_rest_{i}" for i in range(45)]
    + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
)


def _gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.randn(n, 3, generator=g),
        "quats": torch.randn(n, 4, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 4,
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, num_sh_bases(degree) - 1, 3, generator=g),
    }
    return Gaussians(params, torch.rand(n, generator=g) > 0.5, degree)


def inria_load_ply(path, max_sh_degree: int = 3) -> dict[str, torch.Tensor]:
    """``GaussianModel.load_ply`` of graphdeco-inria/gaussian-splatting (scene/gaussian_model.py), on the CPU."""
    plydata = PlyData.read(path)
    xyz = np.stack(
        (
            np.asarray(plydata.elements[0]["x"]),
            np.asarray(plydata.elements[0]["y"]),
            np.asarray(plydata.elements[0]["z"]),
        ),
        axis=1,
    )
    opacities = np.asarray(plydata.elements[0]["opacity"])[..., np.newaxis]
    features_dc = np.zeros((xyz.shape[0], 3, 1))
    features_dc[:, 0, 0] = np.asarray(plydata.elements[0]["f_dc_0"])
    features_dc[:, 1, 0] = np.asarray(plydata.elements[0]["f_dc_1"])
    features_dc[:, 2, 0] = np.asarray(plydata.elements[0]["f_dc_2"])
    extra_f_names = [p.name for p in plydata.elements[0].properties if p.name.startswith("f_rest_")]
    extra_f_names = sorted(extra_f_names, key=lambda x: int(x.split("_")[-1]))
    assert len(extra_f_names) == 3 * (max_sh_degree + 1) ** 2 - 3
    features_extra = np.zeros((xyz.shape[0], len(extra_f_names)))
    for idx, attr_name in enumerate(extra_f_names):
        features_extra[:, idx] = np.asarray(plydata.elements[0][attr_name])
    features_extra = features_extra.reshape((features_extra.shape[0], 3, (max_sh_degree + 1) ** 2 - 1))
    scale_names = sorted(
        (p.name for p in plydata.elements[0].properties if p.name.startswith("scale_")),
        key=lambda x: int(x.split("_")[-1]),
    )
    scales = np.zeros((xyz.shape[0], len(scale_names)))
    for idx, attr_name in enumerate(scale_names):
        scales[:, idx] = np.asarray(plydata.elements[0][attr_name])
    rot_names = sorted(
        (p.name for p in plydata.elements[0].properties if p.name.startswith("rot")),
        key=lambda x: int(x.split("_")[-1]),
    )
    rots = np.zeros((xyz.shape[0], len(rot_names)))
    for idx, attr_name in enumerate(rot_names):
        rots[:, idx] = np.asarray(plydata.elements[0][attr_name])
    return {
        "xyz": torch.tensor(xyz, dtype=torch.float),
        "features_dc": torch.tensor(features_dc, dtype=torch.float).transpose(1, 2).contiguous(),
        "features_rest": torch.tensor(features_extra, dtype=torch.float).transpose(1, 2).contiguous(),
        "opacity": torch.tensor(opacities, dtype=torch.float),
        "scaling": torch.tensor(scales, dtype=torch.float),
        "rotation": torch.tensor(rots, dtype=torch.float),
    }


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_the_inria_load_ply_reads_back_the_gaussians_written(tmp_path, degree):
    g = _gaussians(29, degree)
    path = save_ply(g, tmp_path / "splat.ply")
    loaded = inria_load_ply(str(path))
    p = {k: v.detach() for k, v in g.params.items()}
    assert torch.equal(loaded["xyz"], p["means"])
    assert torch.equal(loaded["features_dc"], p["sh0"])
    rest = torch.zeros(29, 15, 3)  # bands above ``degree`` padded with zeros, as the Inria code stores them
    rest[:, : num_sh_bases(degree) - 1] = p["shN"]
    assert torch.equal(loaded["features_rest"], rest)
    assert torch.equal(loaded["opacity"][:, 0], p["opacities"])
    assert torch.equal(loaded["scaling"], p["scales"])
    assert torch.equal(loaded["rotation"], p["quats"])


def test_records_are_the_248_bytes_of_62_floats_the_sibr_viewer_reads(tmp_path):
    g = _gaussians(7, 3)
    path = save_ply(g, tmp_path / "splat.ply")
    vertex = PlyData.read(str(path))["vertex"]
    assert [p.name for p in vertex.properties] == INRIA_NAMES
    assert all(p.val_dtype == "f4" for p in vertex.properties)
    raw = path.read_bytes()
    header, _, body = raw.partition(b"end_header\n")
    lines = header.decode("ascii").splitlines()
    # SIBR takes the count from the third header line, then reads count fixed 248-byte records after end_header
    assert lines[:3] == ["ply", "format binary_little_endian 1.0", "element vertex 7"]
    assert len(body) == 7 * 248
    records = np.frombuffer(body, dtype="<f4").reshape(7, 62)
    np.testing.assert_array_equal(records[:, 0:3], g.params["means"].detach().numpy())
    np.testing.assert_allclose(np.linalg.norm(records[:, 3:6], axis=1), 1.0, atol=1e-6)  # the normals
    np.testing.assert_array_equal(records[:, 54], g.params["opacities"].detach().numpy())
    np.testing.assert_array_equal(records[:, 58:62], g.params["quats"].detach().numpy())


def test_the_touch_flag_lives_in_a_sidecar_and_defaults_to_vision(tmp_path):
    g = _gaussians(11, 1)
    path = save_ply(g, tmp_path / "splat.ply")
    sidecar = touch_sidecar_path(path)
    assert sidecar == tmp_path / "splat.touch.npy"
    np.testing.assert_array_equal(np.load(sidecar), g.from_touch.numpy())
    assert sorted(p.name for p in tmp_path.iterdir()) == ["splat.ply", "splat.touch.npy"]  # no temporary left
    assert torch.equal(load_ply(path).from_touch, g.from_touch)
    sidecar.unlink()
    assert not load_ply(path).from_touch.any()  # a PLY of any other program: every Gaussian is G_c


def test_a_sidecar_of_another_splat_is_refused_naming_it(tmp_path):
    path = save_ply(_gaussians(11, 0), tmp_path / "splat.ply")
    np.save(touch_sidecar_path(path), np.ones(5, dtype=bool))
    with pytest.raises(SceneFormatError, match="5 flags for 11 Gaussians") as info:
        load_ply(path)
    assert info.value.path == touch_sidecar_path(path)
    touch_sidecar_path(path).write_bytes(b"not an npy file")
    with pytest.raises(SceneFormatError) as info:
        load_ply(path)
    assert info.value.path == touch_sidecar_path(path)


def test_a_degree_is_read_from_the_highest_band_holding_coefficients(tmp_path):
    """Inria files always carry 45 f_rest; lower-degree splats come back at their own degree, and an Inria
    file with zero higher bands at the lowest degree that renders it identically."""
    for degree in (0, 1, 2, 3):
        assert load_ply(save_ply(_gaussians(5, degree), tmp_path / f"d{degree}.ply")).sh_degree == degree


def test_a_splat_of_an_earlier_tacsplat_keeps_its_touch_flags(tmp_path):
    """Earlier versions stored the flag as a 63rd vertex property, ``from_touch`` (uchar)."""
    from plyfile import PlyElement

    g = _gaussians(6, 0)
    vertex = PlyData.read(str(save_ply(g, tmp_path / "new.ply")))["vertex"].data
    dtype = vertex.dtype.descr + [("from_touch", "u1")]
    old = np.empty(len(vertex), dtype=dtype)
    for name in vertex.dtype.names:
        old[name] = vertex[name]
    old["from_touch"] = g.from_touch.numpy()
    PlyData([PlyElement.describe(old, "vertex")]).write(str(tmp_path / "old.ply"))
    assert torch.equal(load_ply(tmp_path / "old.ply").from_touch, g.from_touch)


def test_the_splat_carries_each_gaussians_shortest_axis_as_its_unit_normal(tmp_path):
    """nerfstudio's exported splats have all-zero normals: ours are the flat Gaussians' normals, facing outward."""
    gaussians = _gaussians(200, 1, seed=3)
    vertex = PlyData.read(save_ply(gaussians, tmp_path / "splat.ply"))["vertex"]
    normals = np.stack([np.asarray(vertex[k], np.float64) for k in ("nx", "ny", "nz")], axis=1)
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-6)
    q = torch.nn.functional.normalize(gaussians.params["quats"].detach().double(), dim=-1).numpy()
    for i in range(len(normals)):  # the rotation's column of the smallest scale, to float32 precision
        w, x, y, z = q[i]
        R = np.array(
            [
                [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
            ]
        )
        axis = R[:, int(np.argmin(gaussians.params["scales"][i].detach().numpy()))]
        assert abs(abs(axis @ normals[i]) - 1.0) < 1e-5
    means = gaussians.params["means"].detach().numpy()
    assert np.all(((means - means.mean(axis=0)) * normals).sum(axis=1) >= 0)  # away from the centroid


def test_a_runs_splat_normals_face_out_of_a_torus_hole_too():
    """A torus of opaque surfels seen by cameras all around: a run's splat normals (:func:`facing_normals`) point
    away from the tube's core circle, including on the inner side, where 'away from the centroid' points in."""
    from scipy.spatial.transform import Rotation

    from tacsplat.reconstruction.evaluation import facing_normals
    from tacsplat.reconstruction.meshing import sphere_cameras

    big, small = 0.05, 0.02  # the torus's radii, metres
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 64, endpoint=False), np.linspace(0, 2 * np.pi, 32, endpoint=False))
    u, v = u.ravel(), v.ravel()
    core = np.stack([big * np.cos(u), big * np.sin(u), 0 * u], axis=1)  # [N, 3] the tube's centre line
    out = np.stack([np.cos(v) * np.cos(u), np.cos(v) * np.sin(u), np.sin(v)], axis=1)  # [N, 3] outward normals
    along = np.stack([-np.sin(u), np.cos(u), 0 * u], axis=1)
    flip = np.where(np.random.default_rng(0).random(len(u)) < 0.5, -1.0, 1.0)[:, None]  # the axis's sign is arbitrary
    axes = np.stack([along, np.cross(out, along), flip * out], axis=2)  # columns; the third is the shortest
    axes[:, :, 1] *= flip  # (a rotation: determinant +1)
    n = len(u)
    params = {
        "means": torch.tensor(core + small * out, dtype=torch.float32),
        "quats": torch.tensor(Rotation.from_matrix(axes).as_quat(scalar_first=True), dtype=torch.float32),
        "scales": torch.log(torch.tensor([[0.004, 0.004, 0.0002]] * n)),
        "opacities": torch.full((n,), 4.0),  # (a logit: 0.98)
        "sh0": torch.zeros(n, 1, 3),
        "shN": torch.zeros(n, 0, 3),
    }
    gaussians = Gaussians(params, torch.zeros(n, dtype=torch.bool), 0)
    normals = facing_normals(gaussians, sphere_cameras(np.zeros(3), 0.08, 16, 64), "cpu").numpy()
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)
    outward = (normals * out).sum(axis=1)
    np.testing.assert_allclose(np.abs(outward), 1.0, atol=1e-4)  # the shortest axis, up to its sign
    inner = np.cos(v) < -0.5  # the side facing the hole
    centroid_rule = (params["means"].numpy() * out).sum(axis=1) > 0
    assert centroid_rule[inner].mean() < 0.5  # (what the splat's own centroid would say there)
    assert (outward > 0).mean() >= 0.98 and (outward[inner] > 0).mean() >= 0.95
