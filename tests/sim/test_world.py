import numpy as np
import pytest

from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.sim.world import World, cast_rays

from .helpers import one_room, scenario

ORIGIN = np.array([2.0, 2.0, 1.05])


def world_with(objects=None, **kw):
    data = one_room(**kw)
    if objects is not None:
        data["layouts"] = {"l": {"objects": objects}}
    return World(scenario(data))


def cast(world, direction, origin=ORIGIN, max_range=20.0):
    d = np.asarray(direction, dtype=float)
    r, lab = world.raycast(origin, (d / np.linalg.norm(d))[None], max_range)
    return r[0], int(lab[0])


@pytest.mark.parametrize(
    "direction, expected, cls",
    [
        ([1, 0, 0], 4.0 - 0.05 - 2.0, "wall"),  # wall centred on x = 4, 0.1 m thick
        ([-1, 0, 0], 2.0 - 0.05, "wall"),
        ([0, 1, 0], 4.0 - 0.05 - 2.0, "wall"),
        ([0, 0, -1], 1.05 - 0.05, "floor"),  # floor surface at z = 0.05
        ([0, 0, 1], 0.05 + 2.5 - 1.05, "ceiling"),  # ceiling at floor + 2.5 m
    ],
)
def test_ray_hits_room_surfaces_at_analytic_distance(direction, expected, cls):
    r, lab = cast(world_with(), direction)
    assert r == pytest.approx(expected, abs=1e-9)
    assert lab == CLASS_IDS[cls]


def test_ray_hits_diagonal_wall_at_analytic_distance():
    r, lab = cast(world_with(), [1, 1, 0])
    assert r == pytest.approx(np.sqrt(2) * 1.95, abs=1e-9) and lab == CLASS_IDS["wall"]


def test_ray_hits_box_object_and_rotated_box_and_ellipsoid():
    objects = [
        {"class": "cabinet", "xy": [3.0, 2.0], "size": [0.4, 0.6, 2.0]},  # near face at x = 2.8
        {"class": "table", "xy": [2.0, 3.0], "size": [0.5, 0.5, 2.0], "yaw_deg": 45.0},
        {"class": "plant", "shape": "ellipsoid", "xy": [1.0, 2.0], "size": [0.6, 0.6, 0.6], "elevation": 0.7},
    ]
    w = world_with(objects)
    r, lab = cast(w, [1, 0, 0])
    assert r == pytest.approx(0.8, abs=1e-9) and lab == CLASS_IDS["cabinet"]
    r, lab = cast(w, [0, 1, 0])  # corner of the 45-degree square points at the origin
    assert r == pytest.approx(1.0 - 0.25 * np.sqrt(2), abs=1e-9) and lab == CLASS_IDS["table"]
    r, lab = cast(w, [-1, 0, 0])  # sphere of radius 0.3 centred at (1, 2, 0.05 + 0.7 + 0.3)
    assert r == pytest.approx(0.7, abs=1e-9) and lab == CLASS_IDS["plant"]


def test_rays_beyond_max_range_miss():
    r, lab = cast(world_with(), [1, 0, 0], max_range=1.0)
    assert np.isinf(r) and lab == 0


def test_door_opening_lets_rays_through_and_leaf_is_a_door():
    data = {
        "spaces": [
            {"name": "a", "min": [0.0, 0.0], "max": [4.0, 4.0]},
            {"name": "b", "min": [0.0, 4.0], "max": [4.0, 8.0]},
        ],
        "doors": [{"at": [2.0, 4.0], "width": 1.0}],
        "robots": [{"waypoints": [[2.0, 2.0], [2.0, 6.0]]}],
    }
    w = World(scenario(data))
    r, lab = cast(w, [0, 1, 0])  # through the opening to the far wall of b at y = 8
    assert r == pytest.approx(8.0 - 0.05 - 2.0, abs=1e-9) and lab == CLASS_IDS["wall"]
    assert [o.cls for o in w.objects] == ["door"]
    leaf = w.objects[0]
    assert leaf.centroid[1] < 4.0  # both sides are rooms: the leaf stands in the first one, a
    beside = 2.0 + 1.0 * np.sign(2.0 - leaf.centroid[0])  # the other side of the opening
    r, lab = cast(w, [0, 1, 0], origin=np.array([beside, 2.0, 1.05]))
    assert r == pytest.approx(1.95, abs=1e-9) and lab == CLASS_IDS["wall"]
    r, lab = cast(w, [0, 1, 0], origin=leaf.centroid - [0.0, 1.0, 0.0])  # 1 m in front of the leaf
    assert lab == CLASS_IDS["door"] and r == pytest.approx(1.0 - 0.02, abs=1e-9)


def test_culled_and_unculled_casts_agree():
    w = World(scenario(one_room(layouts={"l": {"objects": [
        {"class": "sofa", "xy": [1.0, 3.0], "size": [1.0, 0.5, 0.8], "yaw_deg": 30.0},
        {"class": "plant", "shape": "ellipsoid", "xy": [3.0, 3.0], "size": [0.5, 0.5, 1.0]},
    ]}})))
    rng = np.random.default_rng(0)
    d = rng.normal(size=(5000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 0] = np.abs(d[:, 0])  # a forward half-space, so the cone cull is active
    r1, l1 = cast_rays(w.static, ORIGIN, d, 3.0)
    r2, l2 = cast_rays(w.static, np.tile(ORIGIN, (len(d), 1)), d, 3.0)
    assert np.array_equal(l1, l2)
    assert np.array_equal(np.isinf(r1), np.isinf(r2))
    assert np.allclose(r1[np.isfinite(r1)], r2[np.isfinite(r2)])


def test_gt_voxel_grid_labels_at_probe_points():
    objects = [{"class": "table", "xy": [3.0, 3.0], "size": [0.8, 0.8, 0.75]}]
    data = one_room(layouts={"l": {"objects": objects}})
    data["spaces"].append({"name": "annex", "min": [4.0, 0.0], "max": [6.0, 2.0]})  # L-shape
    w = World(scenario(data))
    g = w.gt_voxel_grid(0.1)
    assert np.allclose(g.origin / 0.1, np.round(g.origin / 0.1))
    probes = {
        (2.03, 2.03, 1.03): 0,  # free inside the room
        (5.03, 1.03, 1.03): 0,  # free inside the annex
        (3.97, 2.03, 1.03): CLASS_IDS["wall"],  # inside the wall at x = 4
        (0.01, 2.03, 1.03): CLASS_IDS["wall"],
        (2.03, 2.03, 0.01): CLASS_IDS["floor"],
        (2.03, 2.03, 2.57): CLASS_IDS["ceiling"],
        (3.03, 3.03, 0.43): CLASS_IDS["table"],
        (5.03, 3.03, 1.03): -1,  # in the notch of the L: outside the walls
        (-0.5, 2.03, 1.03): -1,  # outside the grid
    }
    pts = np.array(list(probes))
    assert g.label_at(pts).tolist() == list(probes.values())
    # every occupied label is a known class, and all classes placed are present
    present = set(np.unique(g.labels).tolist())
    assert {CLASS_IDS[c] for c in ("wall", "floor", "ceiling", "table")} <= present
    assert present <= {-1, 0, *CLASS_IDS.values()}


def test_gt_voxel_grid_rejects_bad_resolution():
    from kimera_multi_py.core.errors import ConfigError

    with pytest.raises(ConfigError, match="resolution"):
        world_with().gt_voxel_grid(-0.1)
