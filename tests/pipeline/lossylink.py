"""A lossy link for tests: two network namespaces joined by a veth pair that loses packets."""

from __future__ import annotations

import itertools
import os
import shutil
import subprocess

import pytest

LOSS = 0.05
SERVER, CLIENT = "10.213.0.1", "10.213.0.2"


def sh(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(args, capture_output=True, text=True, timeout=30)


def make_lossy(server_ns: str, server_if: str, client_ns: str) -> str | None:
    """Lose LOSS of the packets between the two namespaces: netem where the kernel has it, else an
    iptables rule that drops UDP at random. Returns why neither works, or None."""
    if sh("tc", "-n", server_ns, "qdisc", "add", "dev", server_if, "root", "netem", "loss", f"{LOSS:.0%}").returncode == 0:
        return None
    if shutil.which("iptables") is None:
        return "no netem in this kernel and no iptables (scripts/setup.sh installs it)"
    rule = sh("ip", "netns", "exec", client_ns, "iptables", "-A", "INPUT", "-p", "udp", "-m", "statistic",
              "--mode", "random", "--probability", str(LOSS), "-j", "DROP")
    return None if rule.returncode == 0 else f"no netem, and iptables cannot drop at random: {rule.stderr.strip()}"


@pytest.fixture
def lossy_link():
    """Two network namespaces joined by a veth pair that loses packets: (server's, client's)."""
    if shutil.which("ip") is None:
        pytest.skip("no ip command (iproute2)")
    tag = f"{os.getpid() % 100000}{next(_links)}"
    server, client = f"dcsrv{tag}", f"dccli{tag}"
    made = []
    try:
        for ns in (server, client):
            if sh("ip", "netns", "add", ns).returncode != 0:
                pytest.skip("cannot create network namespaces here (ip netns needs root and netns support)")
            made.append(ns)
        steps = [("ip", "link", "add", f"vs{tag}", "netns", server, "type", "veth", "peer", "name", f"vc{tag}",
                  "netns", client)]
        for ns, iface, address in ((server, f"vs{tag}", SERVER), (client, f"vc{tag}", CLIENT)):
            steps += [("ip", "-n", ns, "addr", "add", f"{address}/24", "dev", iface),
                      ("ip", "-n", ns, "link", "set", iface, "up"), ("ip", "-n", ns, "link", "set", "lo", "up")]
        for step in steps:
            done = sh(*step)
            assert done.returncode == 0, (step, done.stderr)
        why = make_lossy(server, f"vs{tag}", client)
        if why is not None:
            pytest.skip(f"cannot make the link lossy: {why}")
        yield server, client
    finally:
        for ns in made:
            sh("ip", "netns", "del", ns)  # takes its end of the veth pair, and the rules, with it


_links = itertools.count()


