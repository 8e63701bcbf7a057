"""`slscan review`: open anything slscan writes in the Rerun viewer, or serve it on the web
when there is no display (slscan/review_target.py finds the recordings and the blueprint)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

from scanner.errors import ScannerError
from slscan.exit_codes import Exit
from slscan.viewer import DEFAULT_GRPC_PORT, DEFAULT_WEB_PORT


def cmd_review(args: argparse.Namespace) -> int:
    from scanner.session_recording import APPLICATION_ID
    from slscan.review_target import find_target
    from slscan.viewer import review

    target = find_target(args.path)
    print(f"review    {target.describe()}", file=sys.stderr)
    with tempfile.TemporaryDirectory(prefix="slscan-review-") as tmp:
        blueprint = None
        if target.blueprint is not None:
            blueprint = Path(tmp) / f"{target.kind.replace(' ', '_')}.rbl"
            target.blueprint.save(APPLICATION_ID, blueprint)
        code = review(target.recordings, port=args.port, grpc_port=args.grpc_port, blueprint=blueprint)
    if code != 0:  # the viewer's own failure is not a part's: a refused start (exit 2) or a stop by signal
        if code < 0:
            return Exit.INTERRUPTED
        raise ScannerError(f"the Rerun viewer ended with exit code {code} (its messages are above)")
    return Exit.OK


def register(sub: Any) -> None:
    r = sub.add_parser("review")
    r.add_argument("path", help="a folder slscan wrote, or a .rrd recording")
    r.add_argument("--port", type=int, default=None,
                   help=f"headless: the web viewer's HTTP port (default {DEFAULT_WEB_PORT}, or a free one when "
                        f"it is taken)")
    r.add_argument("--grpc-port", type=int, default=None,
                   help=f"the port the viewer's gRPC server listens on (default {DEFAULT_GRPC_PORT}, or a free one "
                        f"when it is taken, as by a second review)")
    r.set_defaults(func=cmd_review)
