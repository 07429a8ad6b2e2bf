"""The tests' port helper: ports from the OS (bound to 0), never the same one twice in a process."""

import socket

from conftest import free_port


def test_free_port_never_hands_out_a_port_twice_and_each_binds():
    # Taken as the kernel gives them, 300 draws repeated a port in 20 of 20 runs here, and 21 draws (seven daemons'
    # three ports, test_serve_lifecycle) in 1 of 200: one way that start-up test could see a port taken.
    ports = [free_port() for _ in range(300)]
    assert len(set(ports)) == len(ports)
    for port in ports[:20]:
        with socket.socket() as s:
            s.bind(("127.0.0.1", port))  # free when drawn: nothing here holds it
