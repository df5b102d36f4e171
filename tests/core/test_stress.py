"""Several plugins and outside threads publishing at once: no delta lost or duplicated, no deadlock."""

from __future__ import annotations

import random
import threading

from erni.blackboard import Agent, Plugin
from erni.blackboard.testing import wait_until
from tests.core.helpers import Item, Recorder

THREADS, PER_THREAD = 6, 150


class Doubler(Plugin):
    """Answers each Item tagged 'in' with an Item tagged 'out' of twice its value."""

    def setup(self):
        self.sub = self.subscribe(Item, where=lambda o: o.tag == "in")

    def execute(self):
        for item in self.sub.added:
            self.add(Item(uid="out-" + item.uid, value=item.value * 2, tag="out"))


class Counter(Plugin):
    """Counts the 'in' items it is told about in one counter object it owns."""

    def setup(self):
        self.counter = self.add(Item(uid="counter", value=0, tag="counter"))
        self.sub = self.subscribe(Item, where=lambda o: o.tag == "in")

    def execute(self):
        if self.sub.added:
            self.counter = self.counter.evolve(value=self.counter.value + len(self.sub.added))
            self.change(self.counter, reports="bump")


def test_concurrent_publishers_lose_and_duplicate_nothing():
    agent = Agent("stress", workers=4)
    recorders = [agent.add_plugin(Recorder, name=f"rec{i}") for i in range(3)]
    agent.add_plugin(Doubler)
    counter = agent.add_plugin(Counter)
    agent.start()
    errors: list[BaseException] = []

    def publisher(n: int) -> None:
        rng = random.Random(n)
        try:
            i = 0
            while i < PER_THREAD:
                batch = rng.randint(1, 5)
                with agent.transaction(f"pub{n}") as tx:
                    for _ in range(min(batch, PER_THREAD - i)):
                        tx.add(Item(uid=f"in-{n}-{i}", value=i, tag="in"))
                        i += 1
                if rng.random() < 0.3:  # some removals and changes of our own objects
                    with agent.transaction() as tx:
                        tx.add(Item(uid=f"tmp-{n}-{i}", value=-1, tag="tmp"))
                    with agent.transaction() as tx:
                        tx.remove(f"tmp-{n}-{i}")
        except BaseException as err:  # pragma: no cover - reported below
            errors.append(err)

    threads = [threading.Thread(target=publisher, args=(n,), name=f"pub{n}") for n in range(THREADS)]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join(30)
        assert not errors
        total = THREADS * PER_THREAD
        wait_until(lambda: len(agent.query(Item, where=lambda o: o.tag == "out")) == total, timeout=20)
        wait_until(lambda: agent.blackboard.get("counter").value == total, timeout=20)
        for rec in recorders:
            wait_until(lambda rec=rec: len(rec.all("added")) - len(rec.all("removed")) ==
                       len(agent.query(Item)), timeout=20)
            added = [o.uid for o in rec.all("added")]
            assert len(added) == len(set(added)), "an add was delivered twice"
            ins = {u for u in added if u.startswith("in-")}
            outs = {u for u in added if u.startswith("out-")}
            assert len(ins) == total and len(outs) == total, "an add was lost"
            tmp_added = {u for u in added if u.startswith("tmp-")}
            tmp_removed = {o.uid for o in rec.all("removed")}
            assert tmp_removed <= tmp_added | set(), "a remove arrived for an object never added"
        assert all(v.value == 2 * int(v.uid.rsplit("-", 1)[1])
                   for v in agent.query(Item, where=lambda o: o.tag == "out"))
        assert counter.failures == 0
    finally:
        agent.stop()
