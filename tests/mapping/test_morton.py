import numpy as np
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from kimera_multi_py.mapping import morton

keys16 = arrays(
    np.int64, st.tuples(st.integers(1, 50), st.just(3)), elements=st.integers(0, morton.KEY_MAX)
)


@given(keys16)
def test_encode_decode_round_trip(keys):
    assert np.array_equal(morton.decode(morton.encode(keys)), keys)


@given(keys16)
def test_child_index_is_octomaps(keys):
    """Child index at level l: x bit + 2 * y bit + 4 * z bit (OctoMap's computeChildIdx)."""
    codes = morton.encode(keys)
    for lev in (0, 5, 15):
        expected = (
            ((keys[:, 0] >> lev) & 1)
            + 2 * ((keys[:, 1] >> lev) & 1)
            + 4 * ((keys[:, 2] >> lev) & 1)
        )
        assert np.array_equal((codes >> (3 * lev)) & 7, expected)


def test_codes_sort_like_the_tree():
    """Every voxel of a node lies in [start, start + 8**level)."""
    keys = np.array([[8, 8, 8], [15, 15, 15], [16, 8, 8]])
    codes = morton.encode(keys)
    start = morton.encode(np.array([[8, 8, 8]]))[0]
    assert start <= codes[1] < start + 8**3
    assert not start <= codes[2] < start + 8**3


def test_points_and_centers():
    pts = np.array([[0.05, -0.05, 1.23], [-3276.9, 0.0, 0.0], [np.nan, 0.0, 0.0]])
    codes = morton.points_to_codes(pts, 0.1)
    assert codes[1] == -1 and codes[2] == -1
    centre = morton.node_centers(codes[:1], np.array([0]), 0.1)[0]
    assert np.allclose(centre, [0.05, -0.05, 1.25])
    big = morton.node_centers(
        np.array([morton.encode(np.array([[32768, 32768, 32768]]))[0]]), np.array([3]), 0.1
    )[0]
    assert np.allclose(big, [0.4, 0.4, 0.4])
    try:
        morton.points_to_keys(pts[1:2], 0.1)
    except ValueError as exc:
        assert "extent" in str(exc)
    else:
        raise AssertionError("out-of-range point accepted")
