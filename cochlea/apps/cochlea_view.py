"""``cochlea-view RUN_DIR [--port P] [--no-open] [--html-out FILE]``: a run replayed in 3-D in
the browser: the robots' links (their own kinematics), the desired and actual tool paths, the
keep-out region, a time slider, play and pause, and the supervisor's stop (docs/logs.md).

It serves one self-contained page (no network needed, nothing fetched) on
``http://127.0.0.1:P/`` (localhost only; port 0, the default, lets the system choose) until
Ctrl-C, and opens it in the default browser unless ``--no-open``; ``--html-out FILE`` writes the
page to FILE instead (written under a hidden temporary name beside it and renamed once
complete) and serves nothing.

Exit codes: 0 done (and after Ctrl-C while serving); 2 (EXIT_USER_ERROR) RUN_DIR is not a
finished run folder or its log is damaged; 3 the port cannot be opened (in use, or not
allowed); 4 ``--html-out`` is not a regular file, or its folder is missing or not writable, or
the write fails. Each is one line on stderr.
"""

from __future__ import annotations

import http.server
import sys
import webbrowser
from pathlib import Path

import numpy as np

from ..console import OneLineParser
from ..errors import EXIT_USER_ERROR, CochleaError, printable
from ..export.run_log import open_run
from ..text import whole_argument
from ..view import DEFAULT_RATE_HZ, build_replay, render_page
from .outputs import atomic_path, check_output_file, interrupted_exit, signals_unwind

PROG = "cochlea-view"
EXIT_PORT = 3
EXIT_HTML_OUT = 4


class OutputError(CochleaError):
    """``--html-out`` cannot be written."""


class PortError(CochleaError):
    """The server's port cannot be opened."""


def check_output(path: Path, run_dir: Path | None = None) -> None:
    """Refuse an output that exists and is not a regular file, or whose folder is missing or
    not writable, or that is one of the files of ``run_dir`` (the run being read); creates
    nothing."""
    check_output_file(path, "--html-out", ".html", OutputError, run_dir=run_dir)


def page_of(run_dir: Path, rate_hz: float = DEFAULT_RATE_HZ) -> tuple[str, dict]:
    """The replay page of ``run_dir`` and its replay."""
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # inf in a log: quiet
        replay = build_replay(open_run(run_dir), rate_hz)
    return render_page(replay), replay


def write_page(page: str, out: Path, run_dir: Path | None = None) -> None:
    check_output(out, run_dir)
    try:
        with atomic_path(out) as tmp:
            tmp.write_text(page, encoding="utf-8")
    except OSError as exc:
        raise OutputError(f"--html-out {out}: cannot write it ({exc.strerror or exc}); "
                          "nothing was left under that name") from None


def make_server(page: str, port: int) -> http.server.HTTPServer:
    """A server of ``page`` at ``/`` (and ``/index.html``) on 127.0.0.1 only."""
    body = page.encode("utf-8")

    class Handler(http.server.BaseHTTPRequestHandler):
        def do_GET(self):  # noqa: N802 - http.server's name
            if self.path.split("?", 1)[0] not in ("/", "/index.html"):
                self.send_error(404, "the replay is at /")
                return
            self.send_response(200)
            self.send_header("Content-Type", "text/html; charset=utf-8")
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args):  # quiet: the terminal shows the URL only
            pass

    try:
        return http.server.ThreadingHTTPServer(("127.0.0.1", port), Handler)
    except OSError as exc:
        raise PortError(f"--port {port}: cannot serve on 127.0.0.1:{port} "
                        f"({exc.strerror or exc}): choose another port, or 0 for any free one"
                        ) from None


def main(argv: list[str] | None = None) -> int:
    parser = OneLineParser(prog=PROG, description=__doc__.split("\n\n")[0])
    parser.add_argument("run_dir", type=Path, metavar="RUN_DIR",
                        help="a run's output folder (cochlea-run or the embedded program)")
    parser.add_argument("--port", type=whole_argument, default=0, metavar="P",
                        help="the port on 127.0.0.1 (default 0: any free port)")
    parser.add_argument("--no-open", action="store_true",
                        help="do not open the page in a browser; print its address only")
    parser.add_argument("--html-out", type=Path, default=None, metavar="FILE",
                        help="write the page to FILE instead of serving it")
    args = parser.parse_args(argv)
    if not 0 <= args.port <= 65535:
        print(f"{PROG}: --port {args.port}: not a port (0..65535)", file=sys.stderr)
        return EXIT_PORT
    try:
        with signals_unwind():  # SIGTERM, SIGHUP: as Ctrl-C, the temporary file removed
            if args.html_out is not None:
                check_output(args.html_out, args.run_dir)
            page, replay = page_of(args.run_dir)
            if args.html_out is not None:
                write_page(page, args.html_out, args.run_dir)
                print(printable(f"{PROG}: wrote {args.html_out}: {len(replay['times'])} "
                                "frames"))
                return 0
            server = make_server(page, args.port)
    except OutputError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_HTML_OUT
    except PortError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_PORT
    except CochleaError as exc:
        print(f"{PROG}: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        word, code = interrupted_exit(exc)
        print(f"{PROG}: {word}; nothing written", file=sys.stderr)
        return code
    url = f"http://127.0.0.1:{server.server_address[1]}/"
    print(printable(f"{PROG}: serving the replay of {args.run_dir} "
                    f"({len(replay['times'])} frames) on {url} until Ctrl-C"), flush=True)
    if not args.no_open:
        webbrowser.open(url)
    try:
        with signals_unwind():  # SIGTERM, SIGHUP: the server closed as after Ctrl-C
            server.serve_forever()
    except KeyboardInterrupt:
        pass
    finally:
        server.server_close()
    return 0


__all__ = ["main", "page_of", "make_server", "check_output", "EXIT_PORT", "EXIT_HTML_OUT"]

if __name__ == "__main__":
    sys.exit(main())
