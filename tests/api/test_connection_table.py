"""The server's connection caps (:class:`api.server.ConnectionTable`): per client, in all, and
the fair share at the cap; and the new settings' bounds."""

from __future__ import annotations

import random

import pytest
from pydantic import ValidationError

from api.server import ConnectionTable, trusted
from service.settings import ServiceSettings


class FakeConnection:
    def __init__(self, name: str, idle: bool = True) -> None:
        self.name = name
        self.idle = idle
        self.evicted = False

    def is_idle(self) -> bool:
        return self.idle

    def evict(self) -> None:
        self.evicted = True

    def __repr__(self) -> str:
        return self.name


def _open(table: ConnectionTable, client: str, n: int, idle: bool = True) -> list[FakeConnection]:
    opened = []
    for i in range(n):
        connection = FakeConnection(f"{client}#{i}", idle)
        if table.admit(connection, client):
            opened.append(connection)
    return opened


def test_a_client_holds_at_most_its_cap_and_others_are_not_touched() -> None:
    table = ConnectionTable(max_total=100, max_per_client=4)
    assert len(_open(table, "10.0.0.1", 10)) == 4
    assert table.closed["client_cap"] == 6
    assert len(_open(table, "10.0.0.2", 2)) == 2
    assert (table.total, table.clients) == (6, 2)
    assert table.held_by("10.0.0.1") == 4


def test_closing_frees_the_place_and_forgets_the_client() -> None:
    table = ConnectionTable(max_total=100, max_per_client=2)
    first, second = _open(table, "10.0.0.1", 2)
    assert not _open(table, "10.0.0.1", 1)
    table.remove(first, "10.0.0.1")
    table.remove(first, "10.0.0.1")  # twice: nothing more
    assert table.total == 1
    assert len(_open(table, "10.0.0.1", 1)) == 1
    table.remove(second, "10.0.0.1")
    assert table.total == 1 and table.clients == 1
    table.remove(FakeConnection("never admitted"), "10.0.0.9")
    assert table.total == 1


def test_at_the_cap_a_newcomer_takes_an_idle_place_of_the_biggest_client() -> None:
    table = ConnectionTable(max_total=8, max_per_client=8)
    busy = _open(table, "flood", 2, idle=False)
    idle = _open(table, "flood", 4, idle=True)
    small = _open(table, "small", 2)
    assert table.total == 8
    (probe,) = _open(table, "probe", 1)  # holds none: takes a place from "flood"
    assert [c for c in busy + idle + small if c.evicted] == [idle[0]]  # oldest idle first
    assert table.held_by("flood") == 5 and table.held_by("probe") == 1
    assert table.closed["evicted"] == 1
    assert table.total == 8
    assert not probe.evicted


def test_a_busy_connection_is_taken_only_from_a_client_with_nothing_idle() -> None:
    table = ConnectionTable(max_total=4, max_per_client=4)
    busy = _open(table, "flood", 3, idle=False)
    _open(table, "other", 1)
    assert len(_open(table, "probe", 1)) == 1
    assert [c.evicted for c in busy] == [True, False, False]  # the oldest
    assert table.held_by("flood") == 2 and table.total == 4


def test_at_the_cap_the_biggest_client_cannot_take_more() -> None:
    table = ConnectionTable(max_total=8, max_per_client=8)
    _open(table, "a", 4)
    _open(table, "b", 4)
    assert not _open(table, "a", 1)  # nobody holds more than "a": refused
    assert table.closed["full"] == 1
    assert table.held_by("b") == 4
    assert len(_open(table, "c", 3)) == 3  # "c" holds less than the biggest each time
    assert sorted(table.held_by(x) for x in "abc") == [2, 3, 3]


def test_a_trusted_proxy_is_exempt_from_the_per_client_cap_only() -> None:
    table = ConnectionTable(max_total=10, max_per_client=2, is_exempt=trusted(["192.0.2.1"]))
    assert len(_open(table, "192.0.2.1", 10)) == 10
    assert len(_open(table, "192.0.2.2", 5)) == 2  # takes places from the proxy, up to its cap
    assert table.total == 10


def test_trusted_matches_addresses_networks_and_any() -> None:
    is_trusted = trusted(["127.0.0.1", "10.0.0.0/8", "::1", "proxy.sock"])
    assert is_trusted("127.0.0.1") and is_trusted("10.1.2.3") and is_trusted("::1")
    assert is_trusted("proxy.sock")
    assert not is_trusted("127.0.0.2") and not is_trusted("192.0.2.1")
    assert not trusted([])("127.0.0.1")
    assert trusted(["*"])("198.51.100.7")


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("http_max_connections_per_client", 0),
        ("http_write_timeout_s", 0.0),
        ("http_write_timeout_s", float("inf")),
    ],
)
def test_settings_refuse_meaningless_limits(field: str, value: float) -> None:
    with pytest.raises(ValidationError, match=field):
        ServiceSettings(policy="min-distance", **{field: value})


def test_settings_from_the_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("TUPA_HTTP_MAX_CONNECTIONS_PER_CLIENT", "5")
    monkeypatch.setenv("TUPA_HTTP_WRITE_TIMEOUT_S", "2.5")
    settings = ServiceSettings(policy="min-distance")
    assert (settings.http_max_connections_per_client, settings.http_write_timeout_s) == (5, 2.5)
    defaults = ServiceSettings.model_fields
    assert (
        defaults["http_max_connections_per_client"].default
        < defaults["http_max_connections"].default
    )


def test_random_opens_and_closes_keep_every_bound() -> None:
    """Against a plain recount after every step: the totals, each client's cap, the overall
    cap, and no client left holding more than a refused newcomer could have taken from."""
    rng = random.Random(7)
    table = ConnectionTable(max_total=20, max_per_client=6)
    open_: dict[str, list[FakeConnection]] = {}
    for step in range(5000):
        client = f"c{rng.randrange(8)}"
        mine = open_.setdefault(client, [])
        if mine and rng.random() < 0.4:
            table.remove(mine.pop(rng.randrange(len(mine))), client)
        else:
            connection = FakeConnection(f"{client}-{step}", idle=rng.random() < 0.5)
            held_before = len(mine)
            biggest_before = max((len(v) for v in open_.values()), default=0)
            if table.admit(connection, client):
                mine.append(connection)
            else:
                assert held_before >= 6 or (
                    sum(map(len, open_.values())) >= 20 and biggest_before <= held_before
                )
            for other, held in open_.items():  # an evicted connection is gone
                for gone in [c for c in held if c.evicted]:
                    held.remove(gone)
                    table.remove(gone, other)  # the protocol's connection_lost: a no-op
        counts = {k: len(v) for k, v in open_.items() if v}
        assert table.total == sum(counts.values()) <= 20
        assert all(table.held_by(k) == n <= 6 for k, n in counts.items())
        assert table.clients == len(counts)
        assert table._biggest == max(counts.values(), default=0)
