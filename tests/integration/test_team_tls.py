"""``kimera-multi certs``: a team CA and a certificate per process (``launch --tls`` is in
test_team_faults.py)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from cryptography import x509
from typer.testing import CliRunner

from kimera_multi_py.cli.main import app

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


def test_the_routers_config_lets_each_certificate_speak_only_for_itself(tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["certs", str(tmp_path / "pki"), "--robots", "2", "--team", "blue"])
    assert res.exit_code == 0, res.output
    acl = json.loads((tmp_path / "pki" / "router.json5").read_text())["access_control"]
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    subjects = {s["id"]: s["cert_common_names"] for s in acl["subjects"]}
    assert subjects["robot1"] == ["robot1"] and subjects["server"] == ["server"]
    assert set(subjects["team"]) == {"robot0", "robot1", "server", "router", "observer"}
    rules = {r["id"]: r for r in acl["rules"]}
    assert rules["speak-robot1"]["key_exprs"] == ["kmp/blue/r1/**", "kmp/blue/alive/r1"]
    assert rules["speak-server"]["key_exprs"] == ["kmp/blue/r999/**", "kmp/blue/alive/r999"]
    assert rules["speak-robot1"]["flows"] == ["ingress"] and "put" in rules["speak-robot1"]["messages"]
    assert "speak-observer" not in rules  # the observer reads only
    policies = {p["id"]: p for p in acl["policies"]}
    assert policies["robot0"] == {"id": "robot0", "rules": ["speak-robot0"], "subjects": ["robot0"]}
    for name in ("robot0", "server", "observer"):  # only the router enforces it
        assert "access_control" not in json.loads((tmp_path / "pki" / f"{name}.json5").read_text())
