"""Corrupt files users hand the CLI: scenario, g2o, DPGO CSV, recorded source,
checkpoint, scene graph and map. Each is one line on stderr naming the file and the problem,
exit code 1, no traceback."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from typer.testing import CliRunner

from kimera_multi_py.cli.main import app
from kimera_multi_py.comms.team import free_ports
from kimera_multi_py.core.errors import KimeraMultiError

REPO = Path(__file__).resolve().parents[1]
TINY = REPO / "sims" / "tiny.toml"
GARBAGE = b"\x00\xff\xfe garbage \x81\xa1v\x01" * 20


def one_line_error(args: list[str], names: str) -> str:
    res = CliRunner().invoke(app, [str(a) for a in args])
    err = res.stderr
    assert res.exit_code == 1, (res.exit_code, res.output, err)
    assert "Traceback" not in res.output + err
    assert res.exception is None or isinstance(res.exception, SystemExit), repr(res.exception)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert names in lines[0], lines[0]
    return lines[0]


@pytest.mark.parametrize("content", [GARBAGE, b"name = 'x'\n[[spaces]\n", b"name = 3\nseed = 'zero'\n", b""])
def test_a_corrupt_scenario(tmp_path, content):
    bad = tmp_path / "scene.toml"
    bad.write_bytes(content)
    one_line_error(["sim", bad, "--out", tmp_path / "o", "--no-rerun"], "scene.toml")


@pytest.mark.parametrize("content", [
    GARBAGE,
    b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nVERTEX_SE3:QUAT 1 1 0 0 0 0 0\n",  # a field short
    b"VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\nEDGE_SE3:QUAT 0 1 1 0 0 0 0 0 1 " + b"1 " * 21 + b"\n",  # unknown vertex 1
    b"VERTEX_SE3:QUAT 0 nan 0 0 0 0 0 1\n",
])
def test_a_corrupt_g2o(tmp_path, content):
    bad = tmp_path / "graph.g2o"
    bad.write_bytes(content)
    one_line_error(["pgo", bad], "graph.g2o")


@pytest.mark.parametrize("cut", ["half", "field", "garbage"])
def test_a_corrupt_dpgo_csv_folder(tmp_path, cut):
    from kimera_multi_py.io.dpgo_csv import write_dpgo_csv
    from kimera_multi_py.io.g2o import read_g2o

    folder = tmp_path / "csv"
    write_dpgo_csv(folder, read_g2o(REPO / "tests" / "data" / "pgo" / "robot_a.g2o"))
    victim = sorted(folder.glob("robot*/measurements.csv"))[-1]
    data = victim.read_bytes()
    if cut == "half":
        data = data[: len(data) // 2]
    elif cut == "field":
        lines = data.splitlines()
        lines[len(lines) // 2] = lines[len(lines) // 2].replace(b",", b",x", 1)
        data = b"\n".join(lines) + b"\n"
    else:
        data = GARBAGE
    victim.write_bytes(data)
    one_line_error(["pgo", folder], str(victim.relative_to(folder)))


def test_a_corrupt_recorded_source_and_checkpoint(tmp_path):
    port = free_ports(1)[0]
    rec = tmp_path / "rec"
    rec.mkdir()
    (rec / "manifest.json").write_bytes(GARBAGE)
    one_line_error(["agent", "--robot", "0", "--source", rec, "--out", tmp_path / "o",
                    "--listen", f"tcp/127.0.0.1:{port}"], "manifest.json")
    (rec / "manifest.json").write_text(json.dumps({"format": "kimera-multi-recording", "version": 99}))
    one_line_error(["agent", "--robot", "0", "--source", rec, "--out", tmp_path / "o",
                    "--listen", f"tcp/127.0.0.1:{port}"], "manifest.json")
    for content in (GARBAGE, b"", b"KMC\x00\x01"):
        ckpt = tmp_path / "run" / "robot0" / "checkpoint.kmc"
        ckpt.parent.mkdir(parents=True, exist_ok=True)
        ckpt.write_bytes(content)
        one_line_error(["agent", "--robot", "0", "--source", f"sim:{TINY}", "--out", tmp_path / "run", "--resume",
                        "--listen", f"tcp/127.0.0.1:{port}"], "checkpoint.kmc")


@pytest.mark.parametrize("content", [GARBAGE, b"{\"nodes\": 3}", b"[]"])
def test_a_corrupt_scene_graph(tmp_path, content):
    (tmp_path / "dsg.json").write_bytes(content)
    one_line_error(["query", str(tmp_path), "room-of", "1"], "dsg.json")


@pytest.mark.parametrize("content", [GARBAGE, b"", b"KMOT"])
def test_a_corrupt_map_names_the_file(tmp_path, content):
    from kimera_multi_py.mapping.octree_io import load_octree

    bad = tmp_path / "map.kmo"
    bad.write_bytes(content)
    with pytest.raises(KimeraMultiError, match="map.kmo"):
        load_octree(bad)
