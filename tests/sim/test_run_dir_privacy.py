"""`erni sim --run-dir`: the run directory and its folders are 0700, every file in them 0600, and
the GUI's token is printed to a terminal only (as `erni agent` prints it), never to a redirected
output or a log: these name the control node's config that holds it."""

from __future__ import annotations

import logging
import os
import stat

from erni.logs import MaskingFormatter, mask_secrets
from tests.sim.test_sim_cli import SimProcess


def test_a_run_directory_is_private_and_its_logs_hold_no_token(tmp_path):
    run = tmp_path / "run"
    (run / "logs").mkdir(parents=True)  # an earlier run's, made under the usual umask
    old = run / "logs" / "control.log"
    old.write_text("an earlier run\n")
    os.chmod(run, 0o755)
    os.chmod(run / "logs", 0o755)
    os.chmod(old, 0o644)
    sim = SimProcess(run, "--robots", "1", "--duration", "2", "--control-port", "0",
                     "--gui-listen", "127.0.0.1:0", headless=False)
    try:
        assert sim.proc.wait(120) == 0, "\n".join(sim.lines)
        sim._reader.join(5)
    finally:
        sim.cleanup()
    # its output is a pipe, not a terminal: the token is not printed, the line says where it is
    line = sim.wait_for("  GUI ", timeout=1)
    token = sim.gui_url().split("?token=")[1]
    assert len(token) >= 16 and token not in "\n".join(sim.lines)
    assert "?token=*** (the token is shown on a terminal only" in line
    modes = {str(p.relative_to(run)): stat.S_IMODE(p.lstat().st_mode) for p in [run, *run.rglob("*")]
             if not p.is_symlink()}
    assert len(modes) > 10 and "journal/control.sqlite" in modes and "keys/cli.pem" in modes, modes
    shared = {name: oct(mode) for name, mode in modes.items() if mode & 0o077}
    assert shared == {}, f"readable by others: {shared}"
    assert all(mode == 0o700 for name, mode in modes.items() if (run / name).is_dir() or name == ".")
    logs = {p.name: p.read_text(errors="replace") for p in (run / "logs").iterdir()}
    assert "control.log" in logs and "ERNI GUI: http://" in logs["control.log"]
    assert [name for name, text in logs.items() if token in text] == []
    assert "?token=*** (the token is shown on a terminal only" in logs["control.log"]


def test_log_lines_show_no_token():
    assert mask_secrets("GUI at http://10.0.0.2:8080/?token=Zx_9-a&x=1; Authorization: Bearer s3cr3t") == \
        "GUI at http://10.0.0.2:8080/?token=***&x=1; Authorization: Bearer ***"
    record = logging.LogRecord("erni.ui", logging.INFO, __file__, 1, "open %s", ("http://h/?token=abc",), None)
    assert MaskingFormatter("%(message)s").format(record) == "open http://h/?token=***"
