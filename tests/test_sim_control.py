"""A simulator's control socket (sim/control.py): its path appears only once it can be connected.

``--sim`` and the tests wait for the control socket's path to exist, then connect to it: a path
made by ``bind()`` before ``listen()`` refused that first connection (seen on a loaded CI host:
"control request failed: Connection refused")."""

from __future__ import annotations

import socket

from crtk_bridge.sim.control import ControlServer, control_request


def test_the_control_socket_path_exists_only_once_it_listens(short_tmp, monkeypatch):
    path = short_tmp / "sim.sock"
    seen = []
    listen = socket.socket.listen

    def listening(sock, *args):
        seen.append(path.exists())  # the path clients wait for, at the moment listen() is called
        return listen(sock, *args)

    monkeypatch.setattr(socket.socket, "listen", listening)
    server = ControlServer(path, lambda request: {"ok": True, "echo": request.get("x")})
    server.start()
    try:
        assert seen == [False]
        assert control_request(path, {"x": 7}) == {"ok": True, "echo": 7}
        assert [p.name for p in short_tmp.iterdir()] == ["sim.sock"]  # no temporary name left
    finally:
        server.stop()
    assert not path.exists()
