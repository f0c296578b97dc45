"""``kimera-multi certs`` and ``launch --tls``: the team's processes over mutual TLS."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
from cryptography import x509
from typer.testing import CliRunner

from kimera_multi_py.cli import app
from kimera_multi_py.sim import Simulation, load_scenario

REPO = Path(__file__).resolve().parents[2]
TINY = REPO / "sims" / "tiny.toml"
pytestmark = pytest.mark.integration


def test_certs_makes_a_ca_and_a_certificate_per_process_signed_by_it(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["certs", str(tmp_path / "pki"), "--robots", "2"])
    assert res.exit_code == 0, res.output
    pki = tmp_path / "pki"
    ca = x509.load_pem_x509_certificate((pki / "ca.pem").read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    for name in ("robot0", "robot1", "server", "router", "observer"):
        cert = x509.load_pem_x509_certificate((pki / f"{name}.pem").read_bytes())
        cert.verify_directly_issued_by(ca)  # raises if another CA signed it
        assert cert.subject.rfc4514_string() == f"CN={name}"
        sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
        assert "localhost" in sans.get_values_for_type(x509.DNSName)
        assert (pki / f"{name}.key").stat().st_mode & 0o077 == 0  # private keys are private
        tls = json.loads((pki / f"{name}.json5").read_text())["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True and tls["connect_certificate"] == str(pki / f"{name}.pem")
    assert not (pki / "robot2.pem").exists()
    bad = CliRunner().invoke(app, ["certs", str(tmp_path / "x"), "--robots", "0"])
    assert bad.exit_code == 1 and "robots" in bad.output and "Traceback" not in bad.output


@pytest.mark.slow
def test_launch_over_mutual_tls_runs_the_team_to_the_end(tmp_path: Path) -> None:
    out = tmp_path / "run"
    res = subprocess.run([sys.executable, "-m", "kimera_multi_py.cli", "launch", str(TINY), "--robots", "2",
                          "--out", str(out), "--tls", "--checkpoint-every", "5"],
                         capture_output=True, text=True, timeout=300, cwd=REPO)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    results = json.loads((out / "results.json").read_text())
    sim = Simulation(load_scenario(TINY, robots=2), seed=0)
    assert [r["keyframes"] for r in results["robots"]] == [len(p.stamps) for p in sim.plans]
    assert results["pgo_runs"] >= 1
    # every process had its own certificate of the new team CA, and required the other end's
    for name in ("robot0", "robot1", "router", "observer"):
        tls = json.loads((out / "certs" / f"{name}.json5").read_text())["transport"]["link"]["tls"]
        assert tls["enable_mtls"] is True and tls["connect_certificate"].endswith(f"{name}.pem")
    for r in range(2):
        assert (out / f"robot{r}" / "trajectory.tum").stat().st_size > 0
