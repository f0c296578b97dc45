"""Corrupt files users hand the CLI (issue 16): scenario, g2o, DPGO CSV, recorded source,
checkpoint, scene graph and map. Each is one line on stderr naming the file and the problem,
exit code 1, no traceback."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from typer.testing import CliRunner

from kimera_multi_py.cli import app
from kimera_multi_py.consensus.zenoh_team import free_ports
from kimera_multi_py.errors import KimeraMultiError

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


def test_a_corrupt_dpgo_csv_folder(tmp_path):
    folder = tmp_path / "csv"
    folder.mkdir()
    good = sorted((REPO.parent / "shared" / "datasets" / "pgo").rglob("*.csv"))
    if good:  # a real folder with one file cut short
        src = good[0].parent
        for f in src.glob("*.csv"):
            shutil.copy(f, folder / f.name)
        first = sorted(folder.glob("*.csv"))[0]
        first.write_bytes(first.read_bytes()[: len(first.read_bytes()) // 2] + b",x,\n")
        one_line_error(["pgo", folder], first.name)
    for f in folder.glob("*.csv"):
        f.unlink()
    (folder / "robot_0.csv").write_bytes(GARBAGE)
    line = CliRunner().invoke(app, ["pgo", str(folder)])
    assert line.exit_code == 1 and "Traceback" not in line.output + line.stderr
    assert len([ln for ln in line.stderr.splitlines() if ln.strip()]) == 1


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
