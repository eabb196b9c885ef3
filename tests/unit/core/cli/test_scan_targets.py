"""``--hosts``, ``--subnet`` and ``--ports`` of ``cellcal devices --scan``: parsed, or refused in one line.

Only loopback addresses appear here; a refused value is never probed.
"""

from __future__ import annotations

import argparse

import pytest

from cellcal.core.cli import main
from cellcal.core.cli.scan_targets import parse_hosts, parse_ports, parse_subnet


def test_a_slash_24_is_its_254_hosts() -> None:
    hosts = parse_subnet("127.0.0.0/24")
    assert len(hosts) == 254 and hosts[0] == "127.0.0.1" and hosts[-1] == "127.0.0.254"
    # host bits set: the subnet around the address
    assert parse_subnet("127.0.0.9/30") == ["127.0.0.9", "127.0.0.10"]
    assert parse_subnet("127.0.0.1/32") == ["127.0.0.1"]
    assert len(parse_subnet("127.0.0.0/22")) == 1022
    assert parse_subnet("::1/128") == ["::1"]


@pytest.mark.parametrize(("text", "message"), [
    ("127.0.0.0/21", "subnet 127.0.0.0/21 has 2048 addresses: at most 1024 (/22) in one scan"),
    ("127.0.0.0/8", "subnet 127.0.0.0/8 has 16777216 addresses: at most 1024 (/22) in one scan"),
    ("::/64", "subnet ::/64 has 18446744073709551616 addresses: at most 1024 (/118) in one scan"),
    ("127.0.0.0/33", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got '127.0.0.0/33'"),
    ("127.0.0.300/24", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got '127.0.0.300/24'"),
    ("127.0.0.0/-1", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got '127.0.0.0/-1'"),
    ("127.0.0.1", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got '127.0.0.1'"),
    ("cell/24", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got 'cell/24'"),
    ("", "expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got ''"),
])
def test_a_bad_subnet_is_refused_with_its_reason(text: str, message: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError) as info:
        parse_subnet(text)
    assert str(info.value) == message


def test_hosts_are_addresses_without_duplicates() -> None:
    assert parse_hosts("127.0.0.1, 127.0.0.2,127.0.0.1,::1") == ["127.0.0.1", "127.0.0.2", "::1"]
    for bad, shown in (("localhost", "'localhost'"), ("127.0.0.1,,127.0.0.2", "''"), ("127.0.0.256", "'127.0.0.256'")):
        with pytest.raises(argparse.ArgumentTypeError) as info:
            parse_hosts(bad)
        assert str(info.value) == f"expected IP addresses separated by commas (no names), got {shown}"
    too_many = ",".join(f"127.0.{i // 256}.{i % 256}" for i in range(1025))
    with pytest.raises(argparse.ArgumentTypeError, match="expected at most 1024 addresses, got 1025"):
        parse_hosts(too_many)


def test_ports_are_name_equals_port() -> None:
    assert parse_ports("xarm=5020, ur-dashboard=29999") == {"xarm": 5020, "ur-dashboard": 29999}
    for bad in ("xarm", "xarm=0", "xarm=65536", "xarm=5e3", "=502", "xarm=\u00b2", "xarm=" + "9" * 5000):
        with pytest.raises(argparse.ArgumentTypeError, match=r"^expected NAME=PORT \(port 1-65535\)"):
            parse_ports(bad)


@pytest.mark.parametrize("argv", [
    ["--scan", "--subnet", "127.0.0.0/8"],
    ["--scan", "--subnet", "127.0.0.0/33"],
    ["--scan", "--hosts", "localhost"],
    ["--scan", "--hosts", "127.0.0.1", "--subnet", "127.0.0.0/24"],
    ["--scan", "--hosts", "127.0.0.1", "--ports", "xarm=0"],
], ids=lambda a: " ".join(a))
def test_the_command_refuses_bad_targets_in_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["devices", *argv])
    captured = capsys.readouterr()
    assert info.value.code == 2
    assert captured.out == ""
    assert len(captured.err.strip().splitlines()) == 1 and "error:" in captured.err


@pytest.mark.parametrize(("argv", "message"), [
    (["--scan", "--hosts", "127.0.0.1", "--ports", "nosuch=1"],
     "cellcal: error: --ports: unknown service 'nosuch' (known: o3r-pcic, o3r-rpc, ur-dashboard, ur-rtde, xarm)"),
    (["--hosts", "127.0.0.1"],
     "cellcal: error: --hosts, --subnet, --factory and --ports say where --scan looks: add --scan"),
], ids=["unknown service", "no --scan"])
def test_targets_that_make_no_sense_are_one_line_before_any_probe(argv: list[str], message: str,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["devices", *argv]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == message + "\n"
