"""Spoken feedback on the control node: espeak-ng run on thread `ui-voice`, never on the blackboard's."""

from __future__ import annotations

import logging
import queue
import shutil
import subprocess
import threading

from erni.plugins.ui.speech import put_dropping_oldest

log = logging.getLogger("erni.ui.voice")


class Speaker:
    """Says short sentences with espeak-ng, one at a time; `say()` never blocks."""

    def __init__(self, *, voice: str = "en-us", speed: int = 165, extra_args: list[str] | None = None,
                 max_queue: int = 8) -> None:
        self.exe = shutil.which("espeak-ng")
        self.args = ["-v", voice, "-s", str(speed), *(extra_args or [])]
        self.queue: queue.Queue[str | None] = queue.Queue(max_queue)
        self.spoken: list[str] = []
        self.failures = 0
        self._proc: subprocess.Popen[bytes] | None = None
        self._thread = threading.Thread(target=self._run, name="ui-voice", daemon=True)

    @property
    def available(self) -> bool:
        """True when espeak-ng is installed."""
        return self.exe is not None

    def start(self) -> Speaker:
        if self.exe is None:
            log.warning("spoken feedback off: espeak-ng is not installed (apt install espeak-ng)")
        else:
            self._thread.start()
        return self

    def say(self, text: str) -> None:
        """Queue a sentence; when the queue is full the sentence is dropped (feedback goes stale)."""
        if self._thread.is_alive():
            try:
                self.queue.put_nowait(text)
            except queue.Full:
                log.info("spoken feedback behind: dropped %r", text)

    def stop(self) -> None:
        """Stop speaking (the current sentence is cut) and join the thread."""
        if not self._thread.is_alive():
            return
        proc = self._proc
        if proc is not None and proc.poll() is None:
            proc.terminate()
        put_dropping_oldest(self.queue, None)  # sentences not yet said are dropped
        self._thread.join(timeout=5)

    def _run(self) -> None:
        assert self.exe is not None
        while (text := self.queue.get()) is not None:
            try:
                self._proc = subprocess.Popen([self.exe, *self.args, "--", text],
                                              stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
                _, err = self._proc.communicate(timeout=15)
                if self._proc.returncode not in (0, -15):
                    self.failures += 1
                    log.warning("espeak-ng failed (%s): %s", self._proc.returncode,
                                err.decode(errors="replace").strip()[:200])
                else:
                    self.spoken.append(text)
            except (OSError, subprocess.TimeoutExpired) as why:
                self.failures += 1
                if self._proc is not None and self._proc.poll() is None:
                    self._proc.kill()
                    self._proc.wait()
                log.warning("espeak-ng failed: %s", why)
            finally:
                self._proc = None
