"""docs/rig.md: the complete rig.toml example is read by Rig.from_file as documented."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from tofloc.errors import FormatError
from tofloc.rig import Rig

DOC = Path(__file__).resolve().parents[1] / "docs" / "rig.md"


def _toml_blocks() -> list[str]:
    return re.findall(r"```toml\n(.*?)```", DOC.read_text(), flags=re.S)


def test_the_complete_example_parses(tmp_path: Path) -> None:
    blocks = _toml_blocks()
    assert len(blocks) == 2
    path = tmp_path / "rig.toml"
    path.write_text(blocks[0])
    rig = Rig.from_file(path)
    assert [s.name for s in rig.sensors] == ["tof0", "tof1", "tof2"]
    assert rig.actuators == ("chamber1", "chamber2", "chamber3")
    assert rig.tolerances.support_yaw_deg == 3.0 and rig.tolerances.range_scale == 0.0
    assert rig.n_zones == 64 and all(s.raw_order.flip_rows and not s.raw_order.transpose for s in rig.sensors)
    # the three sensors sit 120 deg apart around the tip axis, as the text says
    yaw = np.degrees(np.arctan2(rig.T_tip_sensor[:, 1, 2], rig.T_tip_sensor[:, 0, 2]))
    assert np.allclose(np.sort(np.mod(yaw, 360)), [0.0, 120.0, 240.0], atol=1e-3)
    # and the paper's simulated rig is this one (same poses to the printed digits)
    from tofloc.simulation import simulate

    sim_rig = simulate("paper", 0).log.rig
    np.testing.assert_allclose(rig.T_tip_sensor, sim_rig.T_tip_sensor, atol=1e-6)


def test_the_zone_table_example_parses_and_a_typo_is_refused(tmp_path: Path) -> None:
    head = 'actuators = []\n'
    path = tmp_path / "cols.toml"
    path.write_text(head + _toml_blocks()[1])
    rig = Rig.from_file(path)
    assert rig.n_zones == 2 and rig.sensors[0].zone_directions is not None
    bad = tmp_path / "bad.toml"
    bad.write_text(_toml_blocks()[0].replace("support_yaw_deg = 3.0", "support_yaw = 3.0"))
    with pytest.raises(FormatError, match=r"tolerances.support_yaw.*unknown key"):
        Rig.from_file(bad)
