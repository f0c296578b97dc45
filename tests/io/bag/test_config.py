"""The bag config: the README's and docs' examples validate; bad fields name themselves."""

from __future__ import annotations

import re
import tomllib

import pytest

from kimera_multi_py.core.errors import ConfigError
from kimera_multi_py.core.semantics import CLASS_IDS
from kimera_multi_py.io.bag.config import BagConfig, config_for, load_bag_config, read_colour_table
from kimera_multi_py.team.build import bag_spec
from tests.io.bag.conftest import REPO


@pytest.mark.parametrize("doc", ["README.md", "docs/bags.md"])
def test_the_documented_example_config_validates(doc):
    block = re.search(r"```toml\n(# jackal.toml.*?)```", (REPO / doc).read_text(), re.S)
    assert block is not None
    cfg = BagConfig.model_validate(tomllib.loads(block.group(1)))
    assert cfg.motion == "tf" and cfg.class_field == "label" and cfg.max_range == 30.0
    assert cfg.classes is not None
    lut = cfg.class_lut(41)
    assert lut[40] == CLASS_IDS["human"] and lut[3] == 0  # unmapped


def test_yaml_config_and_bad_fields(tmp_path):
    good = tmp_path / "c.yaml"
    good.write_text("depth: /cam/depth\nclasses: {7: chair}\ncolour_table: colours.csv\n")
    cfg = load_bag_config(good)
    assert cfg.camera and cfg.is_optical and cfg.colour_table == tmp_path / "colours.csv"
    bad = tmp_path / "bad.toml"
    bad.write_text('[classes]\n3 = "spaceship"\n')
    with pytest.raises(ConfigError, match=r"classes.*spaceship"):
        load_bag_config(bad)
    bad.write_text('extrinsic = [0, 0, 0, 0, 0, 0, 0]\n')
    with pytest.raises(ConfigError, match="extrinsic"):
        load_bag_config(bad)


def test_a_bags_own_config_is_found_and_a_spec_names_another(tmp_path):
    bag = tmp_path / "run.bag"
    bag.write_bytes(b"")
    assert config_for(bag) == (BagConfig(), None)
    (tmp_path / "run.bag.toml").write_text("max_range = 4.0\n")
    assert config_for(bag)[0].max_range == 4.0
    assert bag_spec(f"bag:{bag}:{tmp_path / 'other.yaml'}") == (bag, tmp_path / "other.yaml")
    assert bag_spec(f"bag:{bag}") == (bag, None)
    with pytest.raises(ConfigError, match="no bag at"):
        bag_spec(f"bag:{tmp_path / 'missing.bag'}")


def test_colour_table(tmp_path):
    table = tmp_path / "t.csv"
    table.write_text("name,red,green,blue,id\nwall,170,170,170,1\nchair,230,25,75,5\n")
    keys, ids = read_colour_table(table)
    assert dict(zip(keys.tolist(), ids.tolist(), strict=True)) == {(170 << 16) | (170 << 8) | 170: 1,
                                                                   (230 << 16) | (25 << 8) | 75: 5}
    table.write_text("wall,170,170,300,1\n")
    with pytest.raises(ConfigError, match="0..255"):
        read_colour_table(table)
