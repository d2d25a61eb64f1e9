"""`bms-estimator batch`: the CLI, the per-drive error list, and Dask distributed with 1 and 2 worker processes."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest

from bms_estimator.cli.__main__ import main
from bms_estimator.errors import EXIT_DATA, EXIT_USAGE
from bms_estimator.fleet.batch import run_batch, summary_rows
from bms_estimator.replay.encode_log import encode_log

N_CELLS = 3
SAMPLES = Path(__file__).parents[2] / "bms_estimator" / "samples"


@pytest.fixture(scope="module")
def fleet(tmp_path_factory):
    d = tmp_path_factory.mktemp("fleet")
    src = SAMPLES / "lg-hg2_25degC_udds_1s.csv.gz"
    for vehicle, seed in (("car1", 0), ("car2", 1)):
        for i, dur in enumerate((200.0, 150.0)):
            out = d / "logs" / vehicle / f"drive{i}.log"
            out.parent.mkdir(parents=True, exist_ok=True)
            encode_log(src, out, N_CELLS, initial_soc=1.0 - 0.05 * i, duration_s=dur, reference_capacity_ah=3.0,
                       seed=seed + i)
    bad = d / "logs" / "car3"
    bad.mkdir()
    (bad / "empty.log").write_bytes(b"")
    (bad / "corrupt.log").write_bytes(b"(0.000000) can0 1B5E0010#A7FF\n(0.01) can0 zz#\x00\xff\n")
    (bad / "foreign.log").write_text("".join(f"({k * 0.01:.6f}) can0 123#0011223344556677\n" for k in range(500)))
    good = (d / "logs" / "car1" / "drive0.log").read_text().splitlines(keepends=True)
    (bad / "backwards.log").write_text("".join(good[:20000] + good[:20000]))  # a second log appended: time rewinds
    cfg = d / "config.toml"
    cfg.write_text(f"""
[pack]
n_cells = {N_CELLS}
capacity_ah = 3.0
ocv_csv = "{SAMPLES / 'lg-hg2_25degC_ocv.csv'}"
[can]
interface = "virtual"
[mqtt]
enabled = false
""")
    return d, cfg


def _read(out: Path) -> dict[str, np.ndarray]:
    return {str(p.relative_to(out)): pq.read_table(p).to_pandas().to_numpy(dtype=float)
            for p in sorted((out / "drives").rglob("*.parquet"))}


def test_cli_reports_bad_logs_and_does_the_rest(fleet, capsys):
    d, cfg = fleet
    out = d / "out-cli"
    rc = main(["batch", str(d / "logs"), "--config", str(cfg), "--out", str(out), "--workers", "1", "--chain",
               "--no-progress"])
    assert rc == 0
    text = capsys.readouterr().out
    assert "4 of 8 drives estimated" in text
    with (out / "errors.csv").open() as fh:
        errors = {Path(r["log"]).name: r["error"] for r in csv.DictReader(fh)}
    assert set(errors) == {"empty.log", "corrupt.log", "foreign.log", "backwards.log"}
    assert "empty log" in errors["empty.log"]
    assert "cannot read the log" in errors["corrupt.log"]
    assert "another DBC" in errors["foreign.log"]
    assert "go back" in errors["backwards.log"]
    with (out / "summary.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    ok = [r for r in rows if r["status"] == "ok"]
    assert len(ok) == 4 * N_CELLS
    assert all(abs(float(r["soc_error_final_pct"])) < 5.0 and float(r["soc_rmse_pct"]) < 5.0 for r in ok)  # encode-log's truth: a reference exists
    assert all(2.0 < float(r["capacity_ah_final"]) < 4.0 and 0 < float(r["r0_ohm_final"]) < 0.1 for r in ok)
    table = pq.read_table(out / "drives" / "car1" / "drive1.log.parquet")
    assert {"soc", "r0_ohm", "tau1_s", "capacity_ah", "temperature_c", "cell", "t_s"} <= set(table.column_names)
    # without --sox: no pack figures (no pack Parquet, no pack columns in the summary)
    assert not list((out / "drives").rglob("*.pack.parquet")) and not any(k.startswith("pack_") for k in rows[0])


def test_cli_errors_name_the_problem(fleet, tmp_path, capsys):
    d, cfg = fleet
    assert main(["batch", str(d / "logs" / "car3" / "empty.log"), "--config", str(cfg), "--out", str(tmp_path),
                 "--workers", "1", "--no-progress"]) == EXIT_DATA
    assert main(["batch", "x.log", "--config", str(tmp_path / "nope.toml"), "--out", str(tmp_path)]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert "empty log" in err and "nope.toml: no such file" in err


def test_an_out_holding_an_earlier_batch_is_refused_unless_overwrite(fleet, capsys):
    """'batch car1 --out DIR' after 'batch car2 --out DIR' rewrote summary.csv for car1 alone and left
    drives/car2/*.parquet beside it, as if of this batch: refused now, or with --overwrite cleared first."""
    d, cfg = fleet
    out = d / "out-again"
    out.mkdir()
    (out / "notes.txt").write_text("mine")  # a folder with other files is no earlier batch
    args = ["--config", str(cfg), "--out", str(out), "--workers", "1", "--no-progress"]
    assert main(["batch", str(d / "logs" / "car2" / "drive1.log"), *args]) == 0
    assert (out / "drives" / "car2" / "drive1.log.parquet").is_file()
    capsys.readouterr()
    assert main(["batch", str(d / "logs" / "car1" / "drive1.log"), *args]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert (f"--out {out}: holds an earlier batch's results (4 files: summary.csv, summary.parquet, errors.csv, ...), "
            "which this batch's would be mixed with: choose an empty directory, or give --overwrite") in err, err
    assert (out / "drives" / "car2" / "drive1.log.parquet").is_file()  # nothing touched
    assert main(["batch", str(d / "logs" / "car1" / "drive1.log"), *args, "--overwrite"]) == 0
    assert sorted(str(p.relative_to(out)) for p in out.rglob("*") if p.is_file()) == [
        "drives/car1/drive1.log.parquet", "errors.csv", "notes.txt", "summary.csv", "summary.parquet"]
    with (out / "summary.csv").open() as fh:
        assert {r["vehicle"] for r in csv.DictReader(fh)} == {"car1"}


def test_two_worker_processes_give_the_one_worker_results(fleet):
    """A real LocalCluster on loopback, 2 worker processes, drives unchained and chained."""
    from dask.distributed import Client, LocalCluster

    d, cfg = fleet
    logs = sorted(str(p) for p in (d / "logs").rglob("*.log") if p.parent.name != "car3")
    for chain in (False, True):
        results = {}
        for n in (1, 2):
            out = d / f"out-{n}-{chain}"
            shutil.rmtree(out, ignore_errors=True)
            with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, host="127.0.0.1",
                              dashboard_address=None) as cluster, Client(cluster) as client:
                assert len(client.scheduler_info()["workers"]) == n
                res = run_batch(logs, str(cfg), out, chain=chain, client=client)
            assert res.workers == n and not res.failed
            results[n] = (_read(out), summary_rows(res.drives))
        files1, rows1 = results[1]
        files2, rows2 = results[2]
        assert len(files1) == 4 and files1.keys() == files2.keys()
        for key in files1:
            assert np.array_equal(files1[key], files2[key], equal_nan=True), key
        assert rows1 == rows2


def test_scheduler_address_puts_the_work_on_that_cluster(fleet, capsys):
    """--scheduler ADDR: the drives run on the cluster behind the address (here a LocalCluster's scheduler)."""
    from dask.distributed import LocalCluster

    d, cfg = fleet
    out = d / "out-sched"
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                      dashboard_address=None) as cluster:
        rc = main(["batch", str(d / "logs" / "car1" / "drive0.log"), "--config", str(cfg), "--out", str(out),
                   "--scheduler", cluster.scheduler_address, "--no-progress"])
    assert rc == 0
    assert "1 of 1 drives estimated" in capsys.readouterr().out
    assert (out / "drives" / "car1" / "drive0.log.parquet").is_file()
    assert main(["batch", str(d / "logs" / "car1" / "drive0.log"), "--config", str(cfg), "--out", str(out) + "-2",
                 "--scheduler", "tcp://127.0.0.1:9", "--no-progress"]) == EXIT_USAGE
    assert "cannot reach the Dask scheduler" in capsys.readouterr().err


def test_cells_the_log_does_not_carry_are_no_data_not_ok(fleet, tmp_path):
    """A configuration with more cells than the logged pack (the example config's 16 on a 3-cell log) gave
    the extra cells rows of status 'ok' with SOC nan; now 'no data' with the reason, and the others as before."""
    from bms_estimator.fleet.drive import run_drive

    d, cfg = fleet
    more = tmp_path / "more.toml"
    more.write_text(cfg.read_text().replace(f"n_cells = {N_CELLS}", f"n_cells = {N_CELLS + 2}"))
    res, _, _ = run_drive(d / "logs" / "car1" / "drive0.log", str(more), tmp_path / "out", "car1")
    assert res.status == "ok", res.error
    rows = summary_rows([res])
    assert [r["status"] for r in rows] == ["ok"] * N_CELLS + ["no data"] * 2
    assert all(np.isfinite(r["soc_final"]) and not r["error"] for r in rows[:N_CELLS])
    assert rows[N_CELLS]["error"] == f"no valid sample of cell {N_CELLS} in the log (pack.n_cells {N_CELLS + 2}: " \
                                      "more cells than the log's pack?)"


def test_logs_of_one_vehicle_name_and_file_name_do_not_overwrite_each_other(fleet, tmp_path, capsys):
    """2023/car1/drive0.log and 2024/car1/drive0.log both wrote drives/car1/drive0.log.parquet: the second
    overwrote the first while the summary listed both drives as estimated. Now the second is skipped, saying why."""
    d, cfg = fleet
    first, second = tmp_path / "2023" / "car1" / "drive0.log", tmp_path / "2024" / "car1" / "drive0.log"
    for src, dst in ((d / "logs" / "car1" / "drive0.log", first), (d / "logs" / "car2" / "drive0.log", second)):
        dst.parent.mkdir(parents=True)
        shutil.copy(src, dst)
    out = tmp_path / "out"
    assert main(["batch", str(tmp_path / "2023"), str(tmp_path / "2024"), "--config", str(cfg), "--out", str(out),
                 "--workers", "1", "--no-progress"]) == 0
    assert "1 of 2 drives estimated" in capsys.readouterr().out
    with (out / "errors.csv").open() as fh:
        errors = list(csv.DictReader(fh))
    assert [(r["vehicle"], r["log"]) for r in errors] == [("car1", str(second))]
    assert errors[0]["error"] == (f"{second}: drives/car1/drive0.log.parquet is already {first}'s (a vehicle folder and "
                                  "a file of the same names): rename one, or batch them separately")
    with (out / "summary.csv").open() as fh:
        ok = [r for r in csv.DictReader(fh) if r["status"] == "ok"]
    table = pq.read_table(out / "drives" / "car1" / "drive0.log.parquet").to_pandas()
    last = table[table["t_s"] == table["t_s"].max()].sort_values("cell")
    assert [float(r["soc_final"]) for r in ok] == last["soc"].tolist()  # the summary's drive is the Parquet's


def test_an_existing_file_named_like_a_glob_is_that_file(tmp_path):
    """A log named 'drive[1].log' given by name was taken as a glob (matching 'drive1.log'): 'matches no file'."""
    from bms_estimator.fleet.batch import expand_inputs

    log = tmp_path / "car1" / "drive[1].log"
    log.parent.mkdir()
    log.write_text("(0.000000) can0 123#00\n")
    assert expand_inputs([str(log)]) == ([str(log)], [])


def test_ctrl_c_reaches_the_batch_not_its_local_workers():
    """Ctrl-C signals the terminal's whole process group: batch's local worker processes too, which died printing
    KeyboardInterrupt tracebacks (asyncio's, the nanny's) while batch closed the cluster. They now ignore SIGINT
    (fleet/worker_setup.py): batch alone stops (exit 130) and closes them."""
    import signal

    from bms_estimator.fleet.batch import _client

    before = signal.getsignal(signal.SIGINT)
    client, cluster = _client(None, 1)
    try:
        seen = client.run(lambda: signal.getsignal(signal.SIGINT) == signal.SIG_IGN)
    finally:
        client.close()
        cluster.close()
    assert list(seen.values()) == [True]
    assert signal.getsignal(signal.SIGINT) is before  # this process's own: Ctrl-C stops the batch


@pytest.mark.parametrize("address, said", [
    ("tls://127.0.0.1:9", "tls:// without Dask's TLS settings"),
    ("inproc://x", "inproc:// is an address inside one process"),
    ("foo", "ValueError: missing port number in address 'foo'"),
    ("ucx://127.0.0.1:9", "the scheme ucx:// is not one batch reaches a scheduler by")])
def test_a_scheduler_address_dask_cannot_use_is_a_usage_error(fleet, tmp_path, capsys, monkeypatch, address, said):
    """--scheduler tls://... without Dask's TLS settings ended in a TypeError traceback (exit 1); inproc://x said
    only 'not enough values to unpack'. Now each is a usage error naming the scheduler, and nothing is written.
    It is told before any Dask Client is made: a Client whose start failed deadlocked the next one's start
    when the garbage collector closed it there (this test hung a CI run)."""
    import dask.distributed
    import distributed

    def no_client(*_a, **_kw):
        raise AssertionError("a Client was made for an address told bad before")

    monkeypatch.setattr(distributed, "Client", no_client)
    monkeypatch.setattr(dask.distributed, "Client", no_client)
    d, cfg = fleet
    out = tmp_path / "out"
    assert main(["batch", str(d / "logs" / "car1" / "drive0.log"), "--config", str(cfg), "--out", str(out),
                 "--scheduler", address, "--no-progress"]) == EXIT_USAGE
    err = capsys.readouterr().err
    assert f"cannot reach the Dask scheduler {address!r}: {said}" in err, err
    assert "an address is tcp://host:port; tls:// needs Dask's TLS settings" in err
    assert not (out / "summary.csv").exists()


def test_cells_of_a_log_without_a_valid_current_are_no_data_for_that_reason(fleet, tmp_path):
    """A log without its current message (PackMeasurement) has every cell's voltage but no valid sample: its
    cells were 'no data' blamed on pack.n_cells ('more cells than the log's pack?'), sending the user to the
    wrong setting. Now the reason is the missing current."""
    from bms_estimator.fleet.drive import run_drive

    d, cfg = fleet
    log = tmp_path / "car1" / "nocurrent.log"
    log.parent.mkdir()
    lines = (d / "logs" / "car1" / "drive0.log").read_text().splitlines(keepends=True)
    log.write_text("".join(line for line in lines if " 1B5E0010#" not in line))
    res, _, _ = run_drive(log, str(cfg), tmp_path / "out", "car1")
    assert res.status == "ok", res.error
    rows = summary_rows([res])
    assert [r["status"] for r in rows] == ["no data"] * N_CELLS
    assert {r["error"] for r in rows} == {f"no sample of the log has a valid current ({res.samples} without one: "
                                          "its current message missing, or flagged invalid?)"}
