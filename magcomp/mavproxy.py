"""magcomp as a MAVProxy module: ``module load magcomp`` (MAVProxy finds the top-level ``mavproxy_magcomp``
package that magcomp installs, which hands over to :func:`init` here).

The module runs the pipeline of ``magcomp run`` on MAVProxy's own link: every message MAVProxy receives goes
through :class:`~magcomp.service.companion.Companion`; MAGCOMP_HEADING and the NAMED_VALUE_FLOAT values
(docs/pilots.md) go out on the master link and on every MAVProxy output, as ``run`` publishes on its master
and ``--out`` links. The console shows a status line per compass (once a second); commands:
``magcomp status`` (the same lines), ``magcomp save`` (write the state now). The state is saved every
``[state] save_interval_s`` and at ``module unload magcomp``.

Settings from the environment (MAVProxy has no per-module command line): ``MAGCOMP_CONFIG`` (a TOML file as
``run --config``), ``MAGCOMP_STATE_DIR`` (default ``$XDG_STATE_HOME/magcomp``, shared with ``run``).

MAVProxy stays optional: this file imports it only when MAVProxy is there; without it (the tests) a
stand-in base class with the same constructor and helpers is used.
"""

from __future__ import annotations

import logging
import os
import time
from typing import Any

from magcomp.errors import MagcompError

try:  # pragma: no cover - depends on MAVProxy being installed
    from MAVProxy.modules.lib.mp_module import MPModule as _Base  # type: ignore[import-not-found]
except ImportError:

    class _Base:  # type: ignore[no-redef]
        """The parts of MAVProxy's MPModule this module uses (constructor, commands, console, master)."""

        def __init__(
            self, mpstate: Any, name: str, description: str | None = None, public: bool = False
        ) -> None:
            self.mpstate = mpstate
            self.name = name
            self.description = description or name
            if public:
                mpstate.public_modules[name] = self

        def add_command(self, name: str, callback: Any, description: str, completions: Any = None) -> None:
            self.mpstate.command_map[name] = (callback, description)
            if completions is not None:
                self.mpstate.completions[name] = completions

        @property
        def console(self) -> Any:
            return self.mpstate.console

        @property
        def master(self) -> Any:
            return self.mpstate.master()


log = logging.getLogger("magcomp.mavproxy")
STATUS_PERIOD_S = 1.0
USAGE = "usage: magcomp <status|save>"


class MagcompModule(_Base):  # type: ignore[misc]
    """``module load magcomp``."""

    def __init__(self, mpstate: Any) -> None:
        what = "magcomp: throttle-driven compass bias removed, corrected heading"
        super().__init__(mpstate, "magcomp", what, public=True)
        from magcomp.adapters.config import load_config
        from magcomp.adapters.state_store import StateStore
        from magcomp.service.companion import Companion
        from magcomp.service.console import default_state_dir

        self.write_errors = 0
        try:
            cfg = load_config(os.environ.get("MAGCOMP_CONFIG") or None)
            store = StateStore(default_state_dir())
        except MagcompError as exc:  # one line on the console; the module then does nothing
            self._say(f"magcomp: {exc}")
            self.companion: Any = None
        else:
            self.companion = Companion(cfg, store, self._send, on_text=self._on_text)
            self._say(f"magcomp: state in {store.directory}; `magcomp status` shows the corrected headings")
        self._next_status = 0.0
        self.add_command("magcomp", self.cmd_magcomp, "magcomp compass compensation", ["<status|save>"])

    # ----------------------------------------------------------------------------------------- output

    def _say(self, text: str) -> None:
        console = getattr(self.mpstate, "console", None)
        if console is not None and hasattr(console, "writeln"):
            console.writeln(text)
        else:
            print(text)

    def _on_text(self, t_s: float, text: str) -> None:
        self._say(f"magcomp: {text}")

    def _send(self, packet: bytes) -> None:
        """To the vehicle's link and to every MAVProxy output (the ground stations behind it)."""
        links = [self.master, *getattr(self.mpstate, "mav_outputs", [])]
        for link in links:
            if link is None:
                continue
            try:
                link.write(packet)
            except OSError as exc:
                self.write_errors += 1
                if self.write_errors == 1:
                    log.warning("magcomp: cannot write to a MAVProxy link: %s", exc)

    # ------------------------------------------------------------------------------------- MAVProxy hooks

    def mavlink_packet(self, m: Any) -> None:
        if self.companion is not None:
            self.companion.handle(m)

    def idle_task(self) -> None:
        now = time.monotonic()
        if self.companion is None or now < self._next_status:
            return
        self._next_status = now + STATUS_PERIOD_S
        set_status = getattr(self.console, "set_status", None)
        if set_status is None or not self.companion.vehicles:
            return
        for row, line in enumerate(self.companion.status_lines()):
            set_status(f"magcomp{row}", line.removeprefix("magcomp "), row=6 + row)

    def cmd_magcomp(self, args: list[str]) -> None:
        if self.companion is None:
            self._say("magcomp: not running (see the error when the module was loaded)")
            return
        if not args or args[0] == "status":
            for line in self.companion.status_lines():
                self._say(line)
        elif args[0] == "save":
            for v in self.companion.vehicles.values():
                for c in v.pipeline.correctors.values():
                    if c.last_t is not None:
                        v.pipeline.persist.save(c, c.last_t)
                v.pipeline.persist.wait()
            self._say(f"magcomp: state saved for {len(self.companion.vehicles)} vehicle(s)")
        else:
            self._say(USAGE)

    def unload(self) -> None:
        if self.companion is not None:
            self.companion.close()
            self._say("magcomp: state saved")
        self.mpstate.command_map.pop("magcomp", None)


def init(mpstate: Any) -> MagcompModule:
    """MAVProxy's entry point for ``module load magcomp``."""
    return MagcompModule(mpstate)
