"""The tests' port helper: free ports outside the range the kernel hands to outgoing connections."""

import socket

from conftest import FIRST_TEST_PORT, _ephemeral_low, free_port


def test_free_ports_lie_below_the_ephemeral_range_and_bind():
    low = _ephemeral_low()
    ports = [free_port() for _ in range(20)]
    assert all(FIRST_TEST_PORT <= p < low for p in ports), (ports, low)
    assert len(set(ports)) > 1, ports  # drawn at random, not one fixed port
    for p in ports[:3]:
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind(("127.0.0.1", p))
            s.listen()


def test_a_port_held_by_a_listener_is_not_handed_out():
    held = []
    try:
        for _ in range(30):
            s = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            s.bind(("127.0.0.1", free_port()))
            s.listen()
            held.append(s)
        taken = {s.getsockname()[1] for s in held}
        assert len(taken) == len(held)
        assert all(free_port() not in taken for _ in range(200))
    finally:
        for s in held:
            s.close()
