"""``inspection store migrate``: an SQLite store copied into a real PostgreSQL server."""

from __future__ import annotations

import socket

import pytest
from test_store import res

from service.cli import main
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
    url = pg_server.new_database()

    assert migrate(data, url) == 0
    out = capsys.readouterr().out
    assert "copied 1234 results" in out and "(1234 new; the database holds 1234)" in out
    with ResultStore(url) as dst:
        assert list(dst.iter_all()) == want
        assert trend(dst, "a", 100, SpcSettings()) == want_trend
        assert dst.last_trigger("line1", "st1") == (1233, want[0].triggered_ns)

    assert migrate(data / "results.sqlite", url) == 0
    assert "(0 new; the database holds 1234)" in capsys.readouterr().out

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
