"""`lca-can-server`'s options: a port out of range is one usage error, not a traceback."""

from __future__ import annotations

import pytest

from lca_sim.cli import can_server


@pytest.mark.parametrize("port", ["99999", "-1", "x"])
def test_a_port_outside_0_to_65535_is_refused_with_the_reason(
    port: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        can_server.main(["--port", port])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "expected a TCP port (0-65535)" in err and "Traceback" not in err


def test_ports_at_the_ends_of_the_range_are_taken() -> None:
    assert can_server._parse_args(["--port", "0"]).port == 0
    assert can_server._parse_args(["--port", "65535"]).port == 65535
