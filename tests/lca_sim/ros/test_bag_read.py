"""The bag reader's refusals: one LcaHilError naming the path and what is wrong (no ROS 2)."""

from __future__ import annotations

from pathlib import Path

import pytest

from lca_sim.errors import LcaHilError
from lca_sim.ros.bag_read import BagReadError, read_bag


def test_bag_read_error_is_the_projects_error() -> None:
    """The tools turn it into one error line like every other LcaHilError."""
    assert issubclass(BagReadError, LcaHilError)


@pytest.mark.parametrize(
    ("make", "said"),
    [
        (lambda p: None, "not found"),
        (lambda p: p.mkdir(), "not a rosbag2 bag"),
        (lambda p: (p.mkdir(), (p / "run_0.mcap").write_bytes(b"\x89MCAP0\r\n")), "--recover"),
        (lambda p: (p.mkdir(), (p / "metadata.yaml").write_text("{")), "cannot read bag"),
    ],
    ids=["missing", "empty folder", "cut short", "bad metadata"],
)
def test_what_is_not_a_readable_bag_is_one_error(tmp_path: Path, make: object, said: str) -> None:
    """A missing folder, one without metadata.yaml, MCAP left by a kill, unreadable metadata."""
    bag = tmp_path / "bag"
    make(bag)  # type: ignore[operator]
    with pytest.raises(BagReadError, match=said) as caught:
        read_bag(bag)
    assert str(bag) in str(caught.value)
