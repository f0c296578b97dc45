"""Person detection where the camera sees little of a person: far away, where a few flipped labels
split the sparse rays on a body, and right in front of the lens, where the view cuts the body off."""

from __future__ import annotations

from collections import Counter

import numpy as np

from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.people import detect_people

HUMAN = CLASS_IDS["human"]
WALL = CLASS_IDS["wall"]


def rays(h_fov_deg=90.0, v_fov_deg=60.0, cols=64, rows=48):
    """A pinhole camera's unit ray directions looking along +x (rows x cols, 3)."""
    az = np.deg2rad(np.linspace(-h_fov_deg / 2, h_fov_deg / 2, cols))
    el = np.deg2rad(np.linspace(-v_fov_deg / 2, v_fov_deg / 2, rows))
    A, E = np.meshgrid(az, el)
    return np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], axis=-1)


def scan(sensor, person_xy, radius=0.25, height=1.8, wall_x=9.5):
    """Every ray's end point and label: an upright cylinder (the person) in front of a wall."""
    d = rays().reshape(-1, 3)
    o = np.asarray(sensor, float)
    c = np.asarray(person_xy, float) - o[:2]
    a = np.sum(d[:, :2] ** 2, axis=1)
    b = -2 * d[:, :2] @ c
    disc = b ** 2 - 4 * a * (c @ c - radius ** 2)
    r_person = np.where(disc >= 0, (-b - np.sqrt(np.maximum(disc, 0))) / (2 * a), np.inf)
    z = o[2] + r_person * d[:, 2]
    r_person[(z < 0) | (z > height) | (r_person <= 0)] = np.inf
    r_wall = (wall_x - o[0]) / d[:, 0]
    person = r_person < r_wall
    r = np.where(person, r_person, r_wall)
    return o + r[:, None] * d, np.where(person, HUMAN, WALL)


def test_a_far_person_split_by_flipped_labels_is_one_detection():
    """At 8 m two columns of rays hit the person, 0.2 m apart, rows 0.17 m apart. Three of them
    flipped to another class (two in one column, the next one up in the other) leave no core point
    within 0.3 m linking the upper and lower body: two clusters, each below ``min_points``, both
    dropped as too small. Linked within ``link_angle`` x the range (0.4 m), it is one person."""
    sensor = np.array([0.0, 0.0, 1.05])
    pts, labels = scan(sensor, [8.0, 0.0])
    person = np.flatnonzero(labels == HUMAN)
    left = person[pts[person, 1] > 0][np.argsort(pts[person[pts[person, 1] > 0], 2])]
    right = person[pts[person, 1] < 0][np.argsort(pts[person[pts[person, 1] < 0], 2])]
    assert len(left) == len(right) >= 9
    i = len(left) // 2 - 1
    flipped = [left[i], left[i + 1], right[i + 2]]
    labels[flipped] = WALL
    dropped: Counter[str] = Counter()
    d = detect_people(pts, labels, [HUMAN], sensor, dropped=dropped)
    assert len(d) == 1 and d.counts[0] == len(person) - 3
    assert np.hypot(*(d.centroids[0, :2] - [8.0, 0.0])) < 0.2
    assert not dropped
    assert len(detect_people(pts, labels, [HUMAN], sensor, link_angle=0.0, dropped=dropped)) == 0
    assert dropped["too_small"] == 2


def test_a_person_right_in_front_of_the_camera_is_detected_and_a_flat_strip_is_not():
    """A third of a metre away the person fills the image from top to bottom, yet the rays on them
    span only a decimetre of height: the view cuts them off, they are not flat."""
    sensor = np.array([0.0, 0.0, 1.0])
    pts, labels = scan(sensor, [0.28, 0.2])
    person = labels == HUMAN
    assert 0 < np.ptp(pts[person, 2]) < 0.25 and (~person).sum() > 500  # below min_height; the wall in view
    dropped: Counter[str] = Counter()
    d = detect_people(pts, labels, [HUMAN], sensor, dropped=dropped)
    assert len(d) == 1 and d.counts[0] == person.sum() and not dropped
    assert np.hypot(*(d.centroids[0, :2] - [0.28, 0.2])) < 0.15
    # a thin strip of human labels across the far wall (two rows of the image) stays too flat
    wall = np.flatnonzero(~person)
    row = wall[np.abs(pts[wall, 2] - 1.0) < 0.15]
    strip = row[np.argsort(np.abs(pts[row, 1]))[:10]]  # five columns wide, nearest straight ahead
    labels = np.full(len(pts), WALL)
    labels[strip] = HUMAN
    d = detect_people(pts, labels, [HUMAN], sensor, dropped=dropped)
    assert len(d) == 0 and dropped["too_flat"] == 1


def test_a_far_person_seen_as_a_sliver_one_ray_wide_is_detected():
    """Half hidden behind someone nearer, a person 7.4 m away shows one column of rays, 0.16 m apart
    in height: each point has two neighbours within 0.3 m, no core point, and the person vanished
    (so that the track of the hidden person took the detection of the one in front). Linked within
    ``link_angle`` x their range (0.37 m), the column is a person."""
    sensor = np.array([0.0, 0.0, 1.05])
    d = rays()[:, 32]  # one column of the image
    pts = sensor + (7.4 / d[:, 0])[:, None] * d
    person = (pts[:, 2] > 0.05) & (pts[:, 2] < 1.8)
    wall = sensor + (9.5 / d[:, 0])[:, None] * d  # the rays above and below hit the wall behind
    pts = np.where(person[:, None], pts, wall)
    labels = np.where(person, HUMAN, WALL)
    assert 10 <= person.sum() <= 12
    dropped: Counter[str] = Counter()
    det = detect_people(pts, labels, [HUMAN], sensor, dropped=dropped)
    assert len(det) == 1 and det.counts[0] == person.sum() and not dropped
    assert abs(det.centroids[0, 0] - 7.5) < 0.2
    # linked within ``radius`` alone (link_angle 0), the column has no core point: nothing
    assert len(detect_people(pts, labels, [HUMAN], sensor, link_angle=0.0)) == 0


def test_a_person_the_side_of_the_image_cuts_is_placed_behind_their_silhouette():
    """A person 2 m away at the image's right edge shows only their left part: the visible points
    lean towards the middle of the image and their mean, pushed back by ``depth_offset``, misses
    the person's axis by 0.2 m. The axis lies a radius behind the silhouette that
    is in view, at right angles to the ray that grazes it."""
    sensor = np.array([0.0, 0.0, 1.0])
    bearing = np.deg2rad(-50.0)  # the image spans -45..45 degrees
    centre = 2.0 * np.array([np.cos(bearing), np.sin(bearing)])
    pts, labels = scan(sensor, centre, radius=0.25)
    assert (labels == HUMAN).sum() >= 20
    cut = detect_people(pts, labels, [HUMAN], sensor, edge_angle=0.0)
    assert len(cut) == 1 and np.hypot(*(cut.centroids[0, :2] - centre)) > 0.15
    d = detect_people(pts, labels, [HUMAN], sensor)
    assert len(d) == 1 and np.hypot(*(d.centroids[0, :2] - centre)) < 0.08
    # a person in the middle of the image keeps the centroid rule
    whole = detect_people(*scan(sensor, [2.0, 0.0]), [HUMAN], sensor)
    np.testing.assert_allclose(whole.centroids, detect_people(*scan(sensor, [2.0, 0.0]), [HUMAN], sensor,
                                                             edge_angle=0.0).centroids)
