"""`erni sim` as a remote operator meets it: the GUI bound to every address prints a URL naming this
host with its token, each agent's PID and the run directory are printed, and the status line
counts only live agents and the robots the control node really hears."""

from __future__ import annotations

import asyncio
from pathlib import Path

from erni.plugins.ui.plugin import is_loopback
from erni.plugins.ui.server import public_address
from tests.sim.test_sim_cli import SimProcess, processes_mentioning
from tests.ui.test_server import get


class GuiSim(SimProcess):
    """`erni sim` with its GUI (the base class runs it headless)."""

    def __init__(self, run_dir: Path, *args: str) -> None:
        super().__init__(run_dir, *args, headless=False)


def test_remote_gui_url_pids_and_an_honest_status_line(tmp_path):
    scenario = tmp_path / "s.toml"
    scenario.write_text('name = "remote"\nduration = 13.0\n[robots]\ncount = 2\n[[failure]]\nat = 1.0\nrobot = "robot2"\n')
    p = GuiSim(tmp_path / "run", str(scenario), "--gui-listen", "0.0.0.0:0", "--control-port", "0")
    try:
        p.wait_for("Ctrl-C stops the team", timeout=90)
        assert f"run directory {tmp_path / 'run'}" in p.wait_for("run directory", timeout=1)
        url = p.gui_url()
        host = url.split("//")[1].split(":")[0]
        assert host == public_address() and "?token=" in url
        if not is_loopback(host):
            assert host != "127.0.0.1"  # a remote operator can open it
        assert asyncio.run(asyncio.wait_for(asyncio.to_thread(get, url), 20))[0] == 200
        assert get(url.split("?")[0])[0] == 403  # not without the token
        agents = set(processes_mentioning(str(tmp_path / "run" / "agents")))
        printed = {int(line.split(" pid ")[1].split()[0]) for line in p.lines if " pid " in line}
        assert printed == agents and len(printed) == 3  # two robots and the control node
        assert p.proc.wait(90) == 0
        status = p.wait_for("robot agents running", timeout=1)
        assert "1/2 robot agents running (robot2 exited); control hears 1/2 (not robot2)" in status, status
    finally:
        p.cleanup()
