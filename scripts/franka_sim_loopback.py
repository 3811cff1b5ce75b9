#!/usr/bin/env python3
"""franka-sim 1.1.7 bound to loopback only (the franka node's fci backend tests against it).

franka-sim's single-arm server has no flag or variable for its bind address: it listens on
0.0.0.0 (TCP command port, default 1337) and leaves its UDP state/command sockets unbound.
This wrapper makes the server bind 127.0.0.1 and binds every UDP socket the server creates
to 127.0.0.1 before use, then runs franka-sim's own command line, so all of its flags work:

    FR3_MJCF=$LABRIG_CACHE/franka-sim/fr3.xml \\
        $LABRIG_FRANKA_SIM_PYTHON scripts/franka_sim_loopback.py --no-gripper --port 21337

(`scripts/setup.sh` installs the venv and writes FR3_MJCF; without it franka-sim would
download its model from GitHub.)
"""
import os
import socket as _socket
import types

HOST = os.environ.get("FRANKA_SIM_HOST", "127.0.0.1")
if not HOST.startswith("127."):
    raise SystemExit(f"franka_sim_loopback: refusing non-loopback FRANKA_SIM_HOST={HOST!r}")
if not os.path.isfile(os.environ.get("FR3_MJCF", "")):
    raise SystemExit("franka_sim_loopback: FR3_MJCF must name the FR3 model (run scripts/setup.sh)")

import franka_sim  # noqa: E402
from franka_sim import franka_sim_server, run_server  # noqa: E402
from franka_sim.gripper import server as _gripper_server  # noqa: E402
from franka_sim.server import state_stream as _state_stream  # noqa: E402


class LoopbackServer(franka_sim_server.FrankaSimServer):
    def __init__(self, *args, **kwargs):
        kwargs["host"] = HOST
        super().__init__(*args, **kwargs)


# The single-arm entry point looks the class up on the package when it starts.
franka_sim.FrankaSimServer = LoopbackServer
franka_sim_server.FrankaSimServer = LoopbackServer


def _udp_on_loopback(family=_socket.AF_INET, type=_socket.SOCK_STREAM, *args, **kwargs):
    s = _socket.socket(family, type, *args, **kwargs)
    if family == _socket.AF_INET and type == _socket.SOCK_DGRAM:
        s.bind((HOST, 0))
    return s


_loopback_socket_module = types.ModuleType("socket_on_loopback")
_loopback_socket_module.__dict__.update(_socket.__dict__)
_loopback_socket_module.socket = _udp_on_loopback
_state_stream.socket = _loopback_socket_module
_gripper_server.socket = _loopback_socket_module

if __name__ == "__main__":
    run_server.main()
