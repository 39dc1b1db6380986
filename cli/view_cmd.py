"""``trianflow-vo view``: open a Rerun recording in the viewer shipped with rerun-sdk.

Before starting the viewer the recording is checked: it must start like a Rerun file and
end like a finished one (a process killed while writing leaves a file without its end of
stream; it is refused unless ``--allow-incomplete``). With ``--web`` the two ports the
viewer listens on (HTTP for the web page, gRPC for the data) are checked first: a busy
default port is replaced by a free one (said on stderr), a busy port given with
``--web-port`` is refused in one line.
"""

from __future__ import annotations

import importlib.util
import socket
import struct
import subprocess
import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors

RRD_MAGIC = b"RRF"  # every .rrd starts with "RRF" and a format digit ("RRF2" in rerun-sdk 0.2x-0.4x)
RRD_FOOTER_MAGIC = b"FOOT"  # a finished file of rerun-sdk >= 0.2x ends with "RRF2FOOT" + a u32 version
_STREAM_HEADER = 12  # "RRF2", 4 bytes of writer version, 4 bytes of encoding options
_MESSAGE_HEADER = 16  # u64 kind, u64 length (little-endian); kind 0 = end of stream
_FOOTER_TRAILER = 32  # after the end-of-stream message of a file with a footer

DEFAULT_WEB_PORT = 9090  # the Rerun CLI's defaults
DEFAULT_GRPC_PORT = 9876


def recording_end(path: Path) -> str | None:
    """None when the recording at ``path`` ends like a finished one, else what is wrong.

    A finished file ends with Rerun's footer marker (``...FOOT`` + version), or (older
    writers, and streams concatenated by ``rerun rrd merge``) its last stream ends with an
    end-of-stream message. Otherwise the message headers are walked (a seek per message,
    payloads are not read): a file that stops at a message boundary or inside a message
    was not closed by its writer.
    """
    size = path.stat().st_size
    with open(path, "rb") as f:
        if size >= 2 * _STREAM_HEADER:
            f.seek(size - 12)
            tail = f.read(8)  # "RRF2FOOT"
            if tail.startswith(RRD_MAGIC) and tail[4:] == RRD_FOOTER_MAGIC:
                return None
        off = 0
        while True:
            f.seek(off)
            head = f.read(_STREAM_HEADER)
            if len(head) < _STREAM_HEADER or not head.startswith(RRD_MAGIC):
                return "it ends inside its header" if off == 0 else "it has data after its end"
            off += _STREAM_HEADER
            while True:
                f.seek(off)
                mh = f.read(_MESSAGE_HEADER)
                if len(mh) < _MESSAGE_HEADER:
                    return ("it ends without Rerun's end-of-stream marker"
                            if len(mh) == 0 else "it ends inside a message")
                kind, length = struct.unpack("<QQ", mh)
                off += _MESSAGE_HEADER + length
                if off > size:
                    return "it ends inside a message"
                if kind == 0:  # end of stream (its payload, if any, is the footer)
                    break
            if length > 0 and off + _FOOTER_TRAILER <= size:
                off += _FOOTER_TRAILER
            if off >= size:
                return None
            f.seek(off)
            if not f.read(4).startswith(RRD_MAGIC):
                return None  # padding after a finished stream: its data is all there


def _check_recording(path: Path, allow_incomplete: bool = False) -> str | None:
    """Raise ``InputError`` unless ``path`` is a readable, finished recording.

    With ``allow_incomplete`` an unfinished one is accepted: the reason is returned
    (for a warning) instead.
    """
    from trianflow_vo.errors import InputError

    if not path.exists():
        raise InputError("no such file", path)
    if not path.is_file():
        raise InputError("not a file (expected a .rrd recording)", path)
    try:
        with open(path, "rb") as f:
            head = f.read(4)
        if not head.startswith(RRD_MAGIC):
            what = "empty file" if not head else "does not start with the Rerun file signature"
            raise InputError(
                f"not a Rerun recording ({what}); write one with `trianflow-vo run SEQ --rerun out.rrd`", path
            )
        problem = recording_end(path)
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
    if problem is None:
        return None
    message = (f"incomplete Rerun recording ({problem}: the process writing it was killed or is still "
               "writing); open what it holds with --allow-incomplete")
    if not allow_incomplete:
        raise InputError(message, path)
    return f"{path}: incomplete Rerun recording ({problem}); opening what it holds"


def _viewer_command() -> list[str]:
    """Command that runs the Rerun CLI of this Python environment (``python -m rerun``)."""
    from trianflow_vo.errors import DependencyError
    from trianflow_vo.viz.rerun_logger import RERUN_INSTALL_HINT

    if importlib.util.find_spec("rerun") is None:
        raise DependencyError(f"rerun-sdk is needed to view recordings: {RERUN_INSTALL_HINT}")
    return [sys.executable, "-m", "rerun"]


def port_is_free(port: int, host: str = "0.0.0.0") -> bool:
    """Whether a listening socket can be bound to ``host:port`` now (as the viewer binds it)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host, port))
        except OSError:
            return False
    return True


def free_port(host: str = "0.0.0.0", avoid: tuple[int, ...] = ()) -> int:
    """A TCP port free on ``host`` now (chosen by the system)."""
    for _ in range(20):
        with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
            port = s.getsockname()[1]
        if port not in avoid:
            return port
    return port


def _web_ports(web_port: int | None) -> tuple[list[str], list[str]]:
    """The viewer's port arguments for ``--web`` and the notes to print.

    Raises:
        click.ClickException: ``--web-port N`` given and N busy.
    """
    notes = []
    if web_port is None:
        web_port = DEFAULT_WEB_PORT
        if not port_is_free(web_port):
            web_port = free_port(avoid=(DEFAULT_GRPC_PORT,))
            notes.append(f"port {DEFAULT_WEB_PORT} is busy (another viewer?): serving the web viewer on port "
                         f"{web_port} instead")
    elif web_port != 0 and not port_is_free(web_port):
        raise click.ClickException(
            f"port {web_port} is busy (another viewer or server listens on it): give another --web-port, "
            "or --web-port 0 for any free port"
        )
    args = ["--web-viewer", "--web-viewer-port", str(web_port)]
    if not port_is_free(DEFAULT_GRPC_PORT):
        grpc = free_port(avoid=(web_port,))
        notes.append(f"port {DEFAULT_GRPC_PORT} is busy (another viewer?): its data server uses port {grpc} instead")
        args += ["--port", str(grpc)]
    return args, notes


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
@click.option("--web-port", type=click.IntRange(0, 65535), default=None,
              help=f"HTTP port of the web viewer (with --web; default {DEFAULT_WEB_PORT}, or a free port when "
                   f"{DEFAULT_WEB_PORT} is busy; 0 = any free port). A busy port given here is refused.")
@click.option("--allow-incomplete", is_flag=True,
              help="Open a recording that was not finished (its writer was killed): what it holds is shown.")
def view(recording: Path, web: bool, web_port: int | None, allow_incomplete: bool):
    """Open a Rerun recording (.rrd) in the viewer.

    Runs the viewer shipped with rerun-sdk and waits until it is closed.
    An unfinished recording (left by a killed run) is refused unless
    --allow-incomplete.
    """
    from trianflow_vo.viz.rerun_logger import no_display_reason

    with user_errors():
        warning = _check_recording(recording, allow_incomplete)
        if warning is not None:
            click.echo(f"warning: {warning}", err=True)
        cmd = _viewer_command() + [str(recording)]
        if web:
            args, notes = _web_ports(web_port)
            cmd += args
            for note in notes:
                click.echo(f"warning: {note}", err=True)
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
