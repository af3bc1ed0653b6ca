"""robot_sim's render process (:class:`services.robot_sim.camera.RenderProcess`):
``python -m services.robot_sim.render_server FD``, FD its end of a socket pair, on which the first message says what
to render; then :func:`services.robot_sim.camera._serve_frames` until the other end closes or says stop."""
from __future__ import annotations

import sys
from multiprocessing.connection import Connection

from services.robot_sim.camera import _serve_frames


def main(fd: int) -> None:
    conn = Connection(fd)
    try:
        what = conn.recv()
    except EOFError:  # robot_sim went before telling us
        return
    _serve_frames(conn, *what)


if __name__ == "__main__":
    main(int(sys.argv[1]))
