"""Where ``cellcal devices --scan`` looks: ``--hosts``, ``--subnet`` and ``--ports`` as argparse types.

Each refuses bad input with one line (exit 2). Hosts are IP address literals only: a name
would need a DNS lookup, which cannot be bounded in time.
"""

from __future__ import annotations

import argparse

__all__ = ["parse_hosts", "parse_ports", "parse_subnet"]

#: Longest option value read, characters (a /22 written out host by host fits).
_MAX_TEXT = 20_000


def _max_hosts() -> int:
    """:data:`cellcal.devices.discovery.MAX_HOSTS`, imported when a value is checked (not at ``cellcal --help``)."""
    from cellcal.devices.discovery import MAX_HOSTS

    return MAX_HOSTS


def parse_hosts(text: str) -> list[str]:
    """``H,H,...``: IPv4 or IPv6 addresses, duplicates dropped, at most :data:`MAX_HOSTS`."""
    import ipaddress  # here and below: not at `cellcal --help`

    max_hosts = _max_hosts()
    if len(text) > _MAX_TEXT:
        raise argparse.ArgumentTypeError(f"expected at most {max_hosts} addresses, got {len(text)} characters")
    hosts: dict[str, None] = {}
    for item in text.split(","):
        item = item.strip()
        try:
            hosts[str(ipaddress.ip_address(item))] = None
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"expected IP addresses separated by commas (no names), got {item[:60]!r}") from None
    if len(hosts) > max_hosts:
        raise argparse.ArgumentTypeError(f"expected at most {max_hosts} addresses, got {len(hosts)}")
    return list(hosts)


def parse_subnet(text: str) -> list[str]:
    """``ADDRESS/PREFIX`` (e.g. ``192.168.1.0/24``): its host addresses, at most :data:`MAX_HOSTS` (a /22).

    Host bits may be set (``192.168.1.7/24`` means the /24 around it); a /31 or /32 (IPv6:
    /127, /128) is its one or two addresses.
    """
    import ipaddress

    max_hosts = _max_hosts()
    shown = text[:60]
    if "/" not in text:
        raise argparse.ArgumentTypeError(f"expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got {shown!r}")
    try:
        net = ipaddress.ip_network(text.strip(), strict=False)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected a subnet ADDRESS/PREFIX such as 192.168.1.0/24, got {shown!r}") from None
    if net.num_addresses > max_hosts:
        smallest = 32 - max_hosts.bit_length() + 1 if net.version == 4 else 128 - max_hosts.bit_length() + 1
        raise argparse.ArgumentTypeError(
            f"subnet {shown} has {net.num_addresses} addresses: at most {max_hosts} (/{smallest}) in one scan")
    return [str(h) for h in net.hosts()]


def parse_ports(text: str) -> dict[str, int]:
    """``NAME=PORT,...``: a port per service name (e.g. ``xarm=5020,ur-dashboard=29999``), ports 1-65535."""
    ports: dict[str, int] = {}
    for item in text.split(","):
        name, sep, value = item.strip().partition("=")
        name, value = name.strip(), value.strip()
        if not (sep and name and value.isascii() and value.isdigit() and len(value) <= 5
                and 1 <= int(value) <= 65535):
            raise argparse.ArgumentTypeError(f"expected NAME=PORT (port 1-65535) separated by commas, "
                                             f"got {item.strip()[:60]!r}")
        ports[name] = int(value)
    return ports
