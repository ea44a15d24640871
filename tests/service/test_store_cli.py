"""``inspection store migrate``: an SQLite store copied into a real PostgreSQL server."""

from __future__ import annotations

import socket

import pytest
from test_store import CAD, res

from service.cli import main
from service.models import Alarm, Baseline, ChartLimits
from service.spc import SpcSettings, trend
from service.store import ResultStore


def migrate(source, target) -> int:
    return main(["store", "migrate", "--from", str(source), "--to", target])


def test_a_data_directory_is_copied_whole_and_a_second_run_copies_nothing_new(
    tmp_path, pg_server, capsys
):
    data = tmp_path / "runs"
    with ResultStore(data / "results.sqlite") as src:
        # More than a page of the copy, two parts, every kind of status.
        statuses = ["pass", "fail", "error", "missed", "not_measurable"]
        src.put_many(
            res(i, part="a" if i % 3 else "b", status=statuses[i % 5]) for i in range(1234)
        )
        want = list(src.iter_all())
        want_trend = trend(src, "a", 100, SpcSettings())
        # Everything else a store holds: alarms (more than a page, one acknowledged), a
        # frozen baseline, and parts created over the API, a retired revision among them.
        alarms = [
            Alarm(
                kind="seq_jump",
                message=f"jump {i}",
                triggered_ns=i,
                line="line1",
                station="st1",
                raised_ns=1000 + i // 2,
            )  # fmt: skip
            for i in range(612)
        ]
        alarms[7] = alarms[7].model_copy(update={"acknowledged_by": "ann", "acknowledged_ns": 5})
        assert src.put_alarms(alarms) == 612
        lim = ChartLimits(center=0.1, sigma=0.02, lcl=0.04, ucl=0.16, spread_center=0.02,
                          spread_lcl=0, spread_ucl=0.07, subgroup=1, n=30, frozen=True)  # fmt: skip
        baseline = Baseline(part="a", since_ns=None, until_ns=9, frozen_ns=10, frozen_by="ann",
                            results=30, limits={"p0": lim})  # fmt: skip
        src.put_baseline(baseline)
        src.add_part("a", '{"name": "a", "version": "1"}', CAD)
        src.retire_part("a")
        src.add_part("a", '{"name": "a", "version": "2"}', CAD[::-1])
        src.add_part("b", '{"name": "b"}', b"solid b\nendsolid b\n")
        parts = [src.part(n, r) for n, r in src.part_revisions()]
    url = pg_server.new_database()

    assert migrate(data, url) == 0
    out = capsys.readouterr().out
    assert "copied 1234 results" in out and "(1234 new; the database holds 1234)" in out
    assert "612 alarms, 1 frozen baselines and 3 part revisions" in out
    with ResultStore(url) as dst:
        assert list(dst.iter_all()) == want
        assert trend(dst, "a", 100, SpcSettings()) == want_trend
        assert dst.last_trigger("line1", "st1") == (1233, want[0].triggered_ns)
        assert list(dst.iter_alarms()) == sorted(alarms, key=lambda a: (a.raised_ns, a.id))
        assert dst.alarm(alarms[7].id).acknowledged_by == "ann"
        assert dst.baselines() == [baseline] and dst.baseline("a").limits["p0"].frozen
        copied = [dst.part(n, r) for n, r in dst.part_revisions()]
        assert [vars(p) for p in copied] == [vars(p) for p in parts]
        assert dst.part_keys() == {"a": parts[1].key, "b": parts[2].key}
        # The copy goes on as the file did: the next creation of "a" is its third revision.
        dst.retire_part("a")
        assert dst.add_part("a", "{}", CAD).revision == 3
        dst.retire_part("a")

    assert migrate(data / "results.sqlite", url) == 0
    out = capsys.readouterr().out
    assert "(0 new; the database holds 1234)" in out and "3 part revisions" in out
    with ResultStore(url) as dst:
        assert len(list(dst.iter_alarms())) == 612 and len(dst.part_revisions()) == 4

    # A result changed in the file since (a re-measured part) replaces its row.
    with ResultStore(data / "results.sqlite") as src:
        src.put(res(5, status="fail"))
    assert migrate(data, url) == 0
    with ResultStore(url) as dst:
        assert dst.count() == 1234 and dst.get(res(5).id).status == "fail"


def _port_nobody_listens_on() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.mark.parametrize(
    "case, message",
    [
        ("to-mysql", "--to: a postgresql://"),
        ("to-a-file", "--to: a postgresql://"),
        ("to-bad-url", "--to: not a valid PostgreSQL URL"),
        ("to-nowhere", "cannot connect"),
        ("from-missing", "--from: no SQLite store at"),
        ("from-empty-dir", "--from: no SQLite store at"),
        ("from-junk", "not a result store"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(tmp_path, capsys, case, message):
    good = tmp_path / "good.sqlite"
    with ResultStore(good) as s:
        s.put(res(1))
    junk = tmp_path / "junk.sqlite"
    junk.write_bytes(b"not sqlite at all" * 100)
    (tmp_path / "empty").mkdir()
    source, target = {
        "to-mysql": (good, "mysql://u:s3cret@db/results"),
        "to-a-file": (good, str(tmp_path / "other.sqlite")),
        "to-bad-url": (good, "postgresql://u:s3cret@db/results?sslmod=require"),
        "to-nowhere": (good, f"postgresql://u:s3cret@127.0.0.1:{_port_nobody_listens_on()}/r"),
        "from-missing": (tmp_path / "absent.sqlite", "postgresql://db/results"),
        "from-empty-dir": (tmp_path / "empty", "postgresql://db/results"),
        "from-junk": (junk, "postgresql://db/results"),
    }[case]
    assert migrate(source, target) == 2
    err = capsys.readouterr().err
    assert err.startswith("inspection store migrate: ") and message in err, err
    assert "Traceback" not in err and "s3cret" not in err


def test_both_ends_are_needed(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["store", "migrate", "--from", "runs"])
    assert exc.value.code == 2
    assert "--to" in capsys.readouterr().err
