"""`run-cell serve`'s ready line names addresses someone can type: a wildcard bind (0.0.0.0, ::) is
listed as the machine's addresses (loopback last), a specific bind address as it is (issue 33, item 8)."""

import re
from types import SimpleNamespace

from cell.access import network
from cell.access.network import reachable_hosts, reachable_urls
from cell.service.config import ServiceConfig
from cell.service.opcua import OpcUaServer
from cell.web.server import ScreenInterface
from tests.serve_process import READY, ServeProcess

# what a line PC may have: loopback (twice, as Debian's /etc/hosts gives the host name 127.0.1.1),
# two plant networks, link-local and global IPv6
MACHINE = [
    "127.0.0.1",
    "192.168.10.5",
    "fe80::1c2:3ff:fe4:5",
    "10.4.0.7",
    "2001:db8::5",
    "::1",
    "127.0.1.1",
    "10.4.0.7",
]


def test_a_wildcard_ipv4_bind_lists_the_machines_ipv4_addresses_loopback_last():
    assert reachable_hosts("0.0.0.0", MACHINE) == ["192.168.10.5", "10.4.0.7", "127.0.0.1"]
    assert reachable_urls("https", "0.0.0.0", 8080, "/", MACHINE) == (
        "https://192.168.10.5:8080/, https://10.4.0.7:8080/, https://127.0.0.1:8080/"
    )
    assert reachable_urls("opc.tcp", "0.0.0.0", 4840, "/cell", MACHINE) == (
        "opc.tcp://192.168.10.5:4840/cell, opc.tcp://10.4.0.7:4840/cell, opc.tcp://127.0.0.1:4840/cell"
    )


def test_a_wildcard_ipv6_bind_lists_the_routable_ipv6_addresses_in_brackets():
    assert reachable_urls("https", "::", 8443, "/", MACHINE) == "https://[2001:db8::5]:8443/, https://[::1]:8443/"


def test_a_wildcard_bind_on_a_machine_with_no_network_names_loopback():
    assert reachable_urls("http", "0.0.0.0", 8080, "/", ["127.0.0.1", "::1"]) == "http://127.0.0.1:8080/"


def test_a_specific_bind_address_prints_as_it_is_whatever_the_machine_has():
    assert reachable_urls("https", "192.168.10.5", 8080, "/", MACHINE) == "https://192.168.10.5:8080/"
    assert reachable_urls("opc.tcp", "cell-7.plant.local", 4840, "/cell", MACHINE) == (
        "opc.tcp://cell-7.plant.local:4840/cell"
    )
    assert reachable_urls("http", "::1", 8080, "/", MACHINE) == "http://[::1]:8080/"


def test_both_interfaces_ready_texts_list_the_machines_addresses_for_a_wildcard_bind(monkeypatch):
    monkeypatch.setattr(network, "machine_addresses", lambda: MACHINE)
    cfg = ServiceConfig(host="0.0.0.0", opcua_port=4841, http_port=8443)
    opcua = OpcUaServer.ready_text.fget(SimpleNamespace(cfg=cfg))  # the property alone: no server started
    assert (
        opcua == "OPC UA opc.tcp://192.168.10.5:4841/cell, opc.tcp://10.4.0.7:4841/cell, opc.tcp://127.0.0.1:4841/cell"
    )
    screen = ScreenInterface.ready_text.fget(
        SimpleNamespace(server=SimpleNamespace(https=True, host="0.0.0.0", port=8443))
    )
    assert screen == "screen https://192.168.10.5:8443/, https://10.4.0.7:8443/, https://127.0.0.1:8443/"


def test_a_real_dry_run_on_loopback_prints_the_same_ready_line_as_before(tmp_path):
    serve = ServeProcess(tmp_path)
    try:
        ready = next(line for line in serve.lines if line.startswith("ready: "))
        http_port = int(serve.url.rsplit(":", 1)[1].rstrip("/"))
        assert re.fullmatch(
            rf"ready: OPC UA opc\.tcp://127\.0\.0\.1:{serve.opcua_port}/cell; screen http://127\.0\.0\.1:{http_port}/ "
            r"\(pid \d+; SIGTERM or Ctrl-C stops safely\)",
            ready,
        ), ready
        assert READY.match(ready) and serve.url == f"http://127.0.0.1:{http_port}/"
    finally:
        assert serve.stop() == 0
