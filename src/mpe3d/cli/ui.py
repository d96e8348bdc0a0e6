"""``mpe3d ui``: the MLflow UI on a tracking store, on 127.0.0.1."""

from __future__ import annotations

import socket
import subprocess
import sys

from mpe3d.cli.options import TRACKING_HELP
from mpe3d.errors import MpeError
from mpe3d.harness.shutdown import EXIT_CODE, stop_group


def add_parser(sub) -> None:
    ui = sub.add_parser("ui", help="start the MLflow UI on the tracking store, on 127.0.0.1")
    ui.add_argument("--tracking-uri", metavar="URI", help=TRACKING_HELP)
    ui.add_argument("--port", type=int, default=5000, help="the port on 127.0.0.1 (default 5000)")
    ui.set_defaults(func=cmd_ui)


def cmd_ui(args) -> int:
    from mpe3d.harness.tracking.store import artifact_root, resolve_uri, serving_uri

    uri = resolve_uri(args.tracking_uri)
    if uri.startswith(("http://", "https://")):
        raise MpeError(f"{uri} is a tracking server: open it in a browser, it serves its own UI")
    with socket.socket() as probe:
        if probe.connect_ex(("127.0.0.1", args.port)) == 0:
            raise MpeError(f"--port: 127.0.0.1:{args.port} is in use; choose another port")
    command = [sys.executable, "-m", "mlflow", "ui", "--backend-store-uri", serving_uri(uri),
               "--host", "127.0.0.1", "--port", str(args.port), "--workers", "1"]  # one user
    root = artifact_root(uri)
    if root:
        command += ["--artifacts-destination", root]
    print(f"MLflow UI at http://127.0.0.1:{args.port}, serving the store {uri}"
          + (f" (artifacts {root})" if root else "") + "; Ctrl-C stops it", flush=True)
    # Its own process group: the server forks workers, and a signal to us must reach them all.
    args.shutdown.line = "mpe3d: interrupted; the MLflow UI is stopped"
    server = subprocess.Popen(command, start_new_session=True)
    try:
        return server.wait()
    except KeyboardInterrupt:
        stop_group(server)
        return EXIT_CODE
