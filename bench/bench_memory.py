"""Where a robot agent's memory goes above the import floor: import by import, then mapping by mapping.

Target 1 of the lean-agent work asks for an idle robot agent's RSS within 1.3x the import floor
of pydantic + pyserial + pysnmp. This prints, in one run on this machine:

  floors     RSS of fresh interpreters that ran `import pydantic, serial, pysnmp.hlapi.v3arch.asyncio`
             (the floor of `bench_agent.py`), then also `from pydantic import BaseModel`, then also one
             model defined (pydantic loads its model machinery lazily: `import pydantic` alone loads
             12 of its modules); and the needed floor of issue 40: pydantic, pyserial and the
             cryptography an agent's identity and sessions use (X.509, Ed25519, X25519, AEAD)
  imports    the agent's packages imported one after another into an interpreter that holds the
             floor and pydantic's machinery, with the RSS each step adds
  started    one robot agent exactly as `erni sim` runs it (`python -m erni.sim.radio CONFIG`),
             after `--settle` seconds: RSS per mapping (anonymous memory, heap, each shared library)
             beside the floor's; then again with glibc's default arenas (8 per core) instead of the one
             arena `erni agent` keeps its threads on

    python bench/bench_memory.py [--settle 15]
"""

from __future__ import annotations

import argparse
import collections
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_agent import FLOOR_IMPORTS  # noqa: E402  # bench/bench_agent.py

from erni.sim.scenario import Scenario  # noqa: E402
from erni.sim.team import Team  # noqa: E402

PYDANTIC_IN_USE = "from pydantic import BaseModel"
ONE_MODEL = "class _Floor(BaseModel):\n    x: int"

# the agent's packages in the order a robot agent imports them
STEPS = [
    ("blackboard (tasks, schemas: the pydantic models)", "erni.blackboard"),
    ("transport (sessions, identities: cryptography's X.509, Ed25519, X25519, AEAD)", "erni.transport"),
    ("motion (ARCOS driver, behaviours)", "erni.plugins.motion.plugin"),
    ("mobinet (SNMP client, BER)", "erni.plugins.mobinet.resource"),
    ("mission", "erni.plugins.mission.plugin"),
    ("agent command and `erni sim`'s radio entry point", "erni.sim.radio"),
]

NEEDED_IMPORTS = ("import pydantic, serial\nfrom cryptography import x509\n"
                  "from cryptography.hazmat.primitives.asymmetric import ed25519, x25519\n"
                  "from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305")
"""What every robot agent must import, whatever ERNI does: its models' library, its robot's serial
port, and its identity and sessions' cryptography (pysnmp, in the older floor, is not imported by
an agent since MobiNet builds its own SNMP PDUs)."""

DEPENDENCIES = ("pydantic", "serial", "cryptography", "msgspec", "sqlite3", "pysnmp", "numpy", "scipy", "matplotlib",
                "networkx", "aiohttp", "websockets", "zenoh", "rosbags", "foxglove", "pocketsphinx", "vosk")
"""ERNI's dependencies by import name (and the standard library's sqlite3, the journal's)."""

WHAT_LOADS = """
import importlib, sys
for mod in sys.argv[2:]:
    importlib.import_module(mod)
deps = sys.argv[1].split(",")
print(len(sys.modules), " ".join(d for d in deps if d in sys.modules), "|", " ".join(d for d in deps if d not in sys.modules))
"""

STEP_PROBE = """
import gc, importlib, sys
def rss():
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS")) / 1024
for mod in sys.argv[1:]:
    importlib.import_module(mod)
    gc.collect()
    print(mod, rss(), flush=True)
"""


def interpreter(code: str) -> collections.Counter[str]:
    """RSS (MB) by mapping of a fresh interpreter that ran `code` and waits."""
    p = subprocess.Popen([sys.executable, "-c", f"{code}\nimport sys; print('ok', flush=True); sys.stdin.read()"],
                         stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, cwd=ROOT)
    assert p.stdout is not None and p.stdin is not None
    p.stdout.readline()
    try:
        return mappings(p.pid)
    finally:
        p.stdin.close()
        p.wait(10)


def mappings(pid: int) -> collections.Counter[str]:
    """RSS (MB) of a process by mapping: [anon], [heap], [stack], or a file's base name."""
    found: collections.Counter[str] = collections.Counter()
    current = "[anon]"
    with open(f"/proc/{pid}/smaps") as f:
        for line in f:
            parts = line.split()
            if parts and "-" in parts[0] and not parts[0].endswith(":"):  # a mapping's header line
                name = parts[5] if len(parts) > 5 else "[anon]"
                current = os.path.basename(name) if name.startswith("/") else name
            elif parts and parts[0] == "Rss:":
                found[current] += int(parts[1]) / 1024
    return found


def started_agent(settle: float, env_extra: dict[str, str]) -> collections.Counter[str]:
    """Mappings of one started robot agent after `settle` seconds."""
    import time

    saved = {k: os.environ.get(k) for k in env_extra}
    os.environ.update(env_extra)  # the team's agents inherit this environment
    team = Team(Scenario(name="bench-memory", robots={"count": 1}), headless=True, control_port=0, ui=False)
    try:
        team.start(timeout=60)
        time.sleep(settle)
        return mappings(team.agents[team.names[0]].proc.pid)
    finally:
        team.stop()
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def main() -> int:
    import results  # bench/results.py, beside this script: the latest results, for the site's benchmarks page

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--settle", type=float, default=15.0, help="seconds a started agent runs before it is measured")
    results.add_argument(ap)
    args = ap.parse_args()

    floor_maps = interpreter(FLOOR_IMPORTS)
    floor = sum(floor_maps.values())
    needed = sum(interpreter(NEEDED_IMPORTS).values())
    in_use = sum(interpreter(f"{FLOOR_IMPORTS}\n{PYDANTIC_IN_USE}").values())
    machinery = sum(interpreter(f"{FLOOR_IMPORTS}\n{PYDANTIC_IN_USE}\n{ONE_MODEL}").values())
    print("floors (RSS of a fresh interpreter)")
    print("| interpreter that ran | RSS MB | above the floor |")
    print("|---|---|---|")
    print(f"| `{FLOOR_IMPORTS}` (the floor) | {floor:.1f} | |")
    print(f"| ... and `{PYDANTIC_IN_USE}` | {in_use:.1f} | +{in_use - floor:.1f} |")
    print(f"| ... and one model defined (pydantic's schema machinery) | {machinery:.1f} | +{machinery - floor:.1f} |")
    print(f"| `{NEEDED_IMPORTS.replace(chr(10), '; ')}` (what an agent must import: the needed floor) | {needed:.1f} | "
          f"{needed - floor:+.1f} |")

    probe = subprocess.run([sys.executable, "-c", f"{FLOOR_IMPORTS}\n{PYDANTIC_IN_USE}\n{ONE_MODEL}\n{STEP_PROBE}",
                            *[mod for _, mod in STEPS]], capture_output=True, text=True, cwd=ROOT, check=True)
    after = {line.split()[0]: float(line.split()[1]) for line in probe.stdout.splitlines() if line.strip()}
    print("\nimports, one after another, into an interpreter holding the floor and pydantic's machinery")
    print("| step | RSS MB after | added MB |")
    print("|---|---|---|")
    last = machinery
    for label, mod in STEPS:
        print(f"| {label} | {after[mod]:.1f} | +{after[mod] - last:.1f} |")
        last = after[mod]
    imports_total = last

    plain = started_agent(args.settle, {})
    default_arenas = started_agent(args.settle, {"MALLOC_ARENA_MAX": str(8 * (os.cpu_count() or 1))})
    total, total_default = sum(plain.values()), sum(default_arenas.values())
    print(f"\nstarted robot agent after {args.settle:.0f} s, RSS by mapping (MB)")
    print("| mapping | agent | floor | agent - floor |")
    print("|---|---|---|---|")
    for name, mb in plain.most_common(10):
        print(f"| {name} | {mb:.2f} | {floor_maps.get(name, 0.0):.2f} | {mb - floor_maps.get(name, 0.0):+.2f} |")
    rest = total - sum(mb for _, mb in plain.most_common(10))
    print(f"| the other mappings | {rest:.2f} | | |")
    print(f"| **all** | **{total:.1f}** | **{sum(floor_maps.values()):.1f}** | |")

    loads = subprocess.run([sys.executable, "-c", WHAT_LOADS, ",".join(DEPENDENCIES), *[mod for _, mod in STEPS]],
                           capture_output=True, text=True, cwd=ROOT, check=True).stdout.split("|")
    count, *loaded = loads[0].split()
    print(f"\nwhat the agent's imports load, in a fresh interpreter: {count} modules; of ERNI's dependencies "
          f"{', '.join(loaded)}; imported only by the part that uses them, when it runs (the journal's sqlite3 "
          f"when it opens; the simulator, GUI, speech, Zenoh wire and ROS 2 bridge otherwise): "
          f"{', '.join(loads[1].split())}")

    print("\nsummary")
    print("| measure | RSS MB | / floor | / floor with pydantic's machinery | / needed floor |")
    print("|---|---|---|---|---|")
    for label, mb in (("the agent's imports alone", imports_total), ("started agent (one malloc arena)", total),
                      ("started agent with glibc's default arenas", total_default)):
        print(f"| {label} | {mb:.1f} | {mb / floor:.2f} | {mb / machinery:.2f} | {mb / needed:.2f} |")
    print(f"| target: 1.3x the floor | {1.3 * floor:.1f} | 1.30 | | |")
    print(f"| target: 1.3x the needed floor | {1.3 * needed:.1f} | | | 1.30 |")
    results.write("bench_memory", [results.target(
        "idle robot agent RSS", "≤ 1.3x the needed import floor", f"what an agent must import, {needed:.1f} MB",
        f"{total / needed:.2f}x ({total:.1f} MB; its imports alone {imports_total / needed:.2f}x)", total / needed <= 1.3)],
        path=args.results, about="an idle robot agent's RSS beside the import floor it needs")
    return 0


if __name__ == "__main__":
    sys.exit(main())
