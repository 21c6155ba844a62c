"""One exception type for bad user input, and the runner that turns it into one ``error:`` line and exit status 2."""

from __future__ import annotations

import sys
import traceback
from pathlib import Path
from typing import Callable, Optional

EXIT_ERROR = 2
"""Every gsticker command's exit status for bad input or a failure (never a result)."""


class GStickerError(Exception):
    """A problem with the user's input; the message names the problem and the fix, on one line."""

    def __init__(self, message: str) -> None:
        super().__init__(" ".join(message.split()))


def print_error(message: str) -> int:
    """Print ``error: <message>`` on one line to stderr; returns :data:`EXIT_ERROR`."""
    sys.stderr.write("error: " + " ".join(str(message).split()) + "\n")
    sys.stderr.flush()
    return EXIT_ERROR


def run_command(body: Callable[[], int], crash: Optional[str] = None) -> int:
    """Run a command's body and return its exit status; bad input (:class:`GStickerError`) and a path that cannot be
    read or written (``OSError``) give one ``error:`` line and exit status 2 instead of a traceback. With ``crash``
    (what a failure means, e.g. "no verdict"), any other exception is one ``error:`` line too, naming it and where it
    was raised."""
    try:
        return body()
    except GStickerError as e:
        return print_error(str(e))
    except OSError as e:
        where = f" ({e.filename})" if getattr(e, "filename", None) else ""
        return print_error(f"{e.strerror or type(e).__name__}{where}; check the paths given and retry")
    except KeyboardInterrupt:
        return print_error("interrupted" + (f"; {crash}" if crash else ""))
    except MemoryError:
        if crash is None:
            raise
        return print_error(f"out of memory; {crash}: use fewer or smaller views and retry")
    except Exception as e:
        if crash is None:
            raise
        frames = traceback.extract_tb(e.__traceback__)
        where = f" at {Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""
        return print_error(
            f"{crash}: {type(e).__name__}: {e}{where} (a failure inside the command, not a result; rerun with the "
            "same inputs to reproduce and report it)"
        )
