"""The optional Rerun SDK: a lazy import, recordings that write `.rrd` files, and the environment of
the Rerun processes n3dmap starts.

rerun-sdk is the `[viz]` extra (`pip install -e ".[viz]"`), not a core dependency: nothing imports it
until a command asks for a recording, and without it the command prints one line naming the extra and
exits 2 (`RerunUnavailable` is an N3dmapError, which the CLI prints that way).

Usage analytics: rerun 0.41 has no environment switch named after analytics. Its viewer and CLI (the
`rerun` binary; the SDK itself records nothing when it only writes files) keep analytics off when the
user ran `rerun analytics disable` or when the variable `CI` is set (re_analytics' pipeline checks
both). n3dmap therefore sets `CI=1` in the environment of every Rerun process it starts (the viewer of
`--spawn`, the web server of `--serve-web`, `rerun rrd` in tests) unless `N3DMAP_RERUN_ANALYTICS=1`
asks to leave Rerun's own default alone; it never changes the user's Rerun configuration. Nothing here
needs the network.
"""

from __future__ import annotations

import os
import shutil
import sys
import uuid
from pathlib import Path

from core.errors import N3dmapError

INSTALL_HINT = "install the viz extra: pip install -e '.[viz]'"
APPLICATION_ID = "n3dmap"


class RerunUnavailable(N3dmapError):
    """rerun-sdk is not installed (the `[viz]` extra)."""


def require_rerun():
    """The `rerun` module, or RerunUnavailable with the one line that says how to get it."""
    try:
        import rerun
    except ImportError:
        hint = INSTALL_HINT
        if sys.version_info < (3, 11):
            hint += " (rerun-sdk 0.41 needs Python >= 3.11)"
        raise RerunUnavailable(hint) from None
    return rerun


def viewer_env(base: dict[str, str] | None = None) -> dict[str, str]:
    """Environment for a `rerun` process n3dmap starts: analytics off (see the module doc)."""
    env = dict(os.environ if base is None else base)
    if env.get("N3DMAP_RERUN_ANALYTICS", "") not in ("1", "on", "true"):
        env["CI"] = env.get("CI") or "1"
    return env


def rerun_executable() -> str:
    """Path of the `rerun` binary shipped in the rerun-sdk wheel (package `rerun_cli`). Not the `rerun`
    console script: that is a Python wrapper which runs the binary as its child, so stopping the
    wrapper's PID would leave the binary (a viewer, a web server) running."""
    require_rerun()
    import rerun_cli  # ships with rerun-sdk

    binary = Path(rerun_cli.__file__).with_name("rerun")
    if not binary.is_file():
        found = shutil.which("rerun")
        if found is None:
            raise RerunUnavailable(f"rerun-sdk is installed but its viewer binary is missing ({binary}); {INSTALL_HINT}")
        return found
    return str(binary)


def check_rrd_path(path: str | os.PathLike, *, flag: str = "--rerun") -> Path:
    """Check that `.rrd` output can be written at `path` before any slow work starts: not a directory,
    its folder creatable, the file writable. Returns the path; OSError/N3dmapError name it."""
    out = Path(path)
    if out.is_dir():
        raise N3dmapError(f"{flag} {out} is a directory; give the .rrd file to write (e.g. {out / 'recording.rrd'})")
    if out.suffix != ".rrd":
        raise N3dmapError(f"{flag} {out}: a Rerun recording file must end in .rrd")
    existed = out.exists()
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        with open(out, "ab"):
            pass
        if not existed:  # a probe only: a run that fails later leaves no empty recording behind
            out.unlink()
    except OSError as e:
        raise N3dmapError(f"{flag} {out}: cannot write there ({e.strerror or e})") from None
    return out


def open_recording(*, name: str, save_to: str | os.PathLike | None = None, recording_id: str | None = None):
    """A new `rerun.RecordingStream` (not the process-global one, so several can coexist in tests),
    named `name`, writing to `save_to` (an .rrd file) when given; other sinks are attached by the
    caller. Log time is off: every entity is indexed by n3dmap's own timelines (rerun_paths)."""
    rr = require_rerun()
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id or uuid.uuid4().hex)
    rec.send_recording_name(name)
    rec.set_log_time_enabled(False)
    if save_to is not None:
        rec.save(str(save_to))
    return rec


def close_recording(rec) -> None:
    """Flush everything logged and finalise the sinks (an .rrd file gets its footer)."""
    rec.flush()
    rec.disconnect()
