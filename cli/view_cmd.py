"""``trianflow-vo view``: open a Rerun recording in the viewer shipped with rerun-sdk."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors

RRD_MAGIC = b"RRF"  # every .rrd starts with "RRF" and a format digit ("RRF2" in rerun-sdk 0.2x-0.4x)


def _check_recording(path: Path) -> None:
    """Raise ``InputError`` unless ``path`` is a readable file that starts like a recording."""
    from trianflow_vo.errors import InputError

    if not path.exists():
        raise InputError("no such file", path)
    if not path.is_file():
        raise InputError("not a file (expected a .rrd recording)", path)
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
    if not head.startswith(RRD_MAGIC):
        what = "empty file" if not head else "does not start with the Rerun file signature"
        raise InputError(f"not a Rerun recording ({what}); write one with `trianflow-vo run SEQ --rerun out.rrd`", path)


def _viewer_command() -> list[str]:
    """Command that runs the Rerun CLI of this Python environment (``python -m rerun``)."""
    from trianflow_vo.errors import DependencyError
    from trianflow_vo.viz.rerun_logger import RERUN_INSTALL_HINT

    if importlib.util.find_spec("rerun") is None:
        raise DependencyError(f"rerun-sdk is needed to view recordings: {RERUN_INSTALL_HINT}")
    return [sys.executable, "-m", "rerun"]


@click.command(
    "view",
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog="""\b
Examples:
  trianflow-vo view runs/kitti00/out.rrd
  trianflow-vo view out.rrd --web          # no display: serve it to a browser
""",
)
@click.argument("recording", type=click.Path(path_type=Path))
@click.option("--web", is_flag=True,
              help="Serve the recording to the Rerun web viewer (open the printed URL in a browser) "
                   "instead of opening a native window; works without a display.")
@click.option("--web-port", type=click.IntRange(0, 65535), default=9090, show_default=True,
              help="HTTP port of the web viewer (with --web; 0 = any free port).")
def view(recording: Path, web: bool, web_port: int):
    """Open a Rerun recording (.rrd) in the viewer.

    Runs the viewer shipped with rerun-sdk and waits until it is closed.
    """
    from trianflow_vo.viz.rerun_logger import no_display_reason

    with user_errors():
        _check_recording(recording)
        cmd = _viewer_command() + [str(recording)]
        if web:
            cmd += ["--web-viewer", "--web-viewer-port", str(web_port)]
        else:
            reason = no_display_reason()
            if reason is not None:
                raise click.ClickException(
                    f"cannot open the Rerun viewer: {reason}. Use `trianflow-vo view {recording} --web` "
                    f"(or `rerun {recording} --web-viewer`) and open the printed URL in a browser, "
                    "or copy the file to a machine with a display."
                )
        try:
            rc = subprocess.call(cmd)
        except KeyboardInterrupt:
            rc = 0  # the user closed it from the terminal
        except OSError as exc:
            raise click.ClickException(f"cannot start the Rerun viewer ({cmd[0]}): {exc.strerror or exc}") from None
        if rc != 0:
            hint = "" if web else "; without a working display try --web"
            raise click.ClickException(f"the Rerun viewer exited with status {rc} while opening {recording}{hint}")
