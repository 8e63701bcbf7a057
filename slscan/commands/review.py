"""`slscan review`: open a session's recording in the Rerun viewer, or serve it on the web
when there is no display."""

from __future__ import annotations

import argparse
from typing import Any

from scanner.errors import ScannerError


def cmd_review(args: argparse.Namespace) -> int:
    from scanner.multiview import MultiViewSession, is_multiview
    from scanner.session import RECORDING, Session
    from slscan.viewer import review

    session = (MultiViewSession.open(args.session, partial=True) if is_multiview(args.session)
               else Session.open(args.session))
    path = session.root / RECORDING
    if not path.exists():
        raise ScannerError(f"{path}: no recording; run `slscan decode {session.root}` to make one")
    return review(path, port=args.port)


def register(sub: Any) -> None:
    r = sub.add_parser("review", help="open a session's recording in the Rerun viewer (web when headless)")
    r.add_argument("session")
    r.add_argument("--port", type=int, default=9090)
    r.set_defaults(func=cmd_review)
