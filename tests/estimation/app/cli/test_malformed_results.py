"""Family 3: damaged results for evaluate, and damaged iSAM2 checkpoints for isam --resume.

``report.json``, the result folder, ``map.npz`` (corrupt, truncated, a zip bomb, many nearly
empty blocks), ``poses/<robot>.tum`` and the checkpoint: one line each, memory bounded.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.estimation.app.cli.malformed import (
    Case,
    Guarded,
    Setup,
    Workspace,
    cases_param,
    copy,
    directory,
    edit,
    execute,
    fifo,
    json_file,
    remove,
    run_guarded,
    simulated_dataset,
    symlink,
    workspace,
    write,
)

REPORT = "{ds}/result/report.json"
MAP = "{ds}/result/map.npz"
POSES = "{ds}/result/poses/a.tum"
CHECKPOINT = "{ds}/.result_isam.checkpoint.npz"
EVALUATE = ("evaluate", "{ds}")
RESUME = ("isam", "{ds}", "--resume")


def sparse(rel: str, size: int) -> Setup:
    def setup(ws: Workspace) -> None:
        with open(rel.format(**ws.fields()), "r+b") as handle:
            handle.truncate(size)

    return setup


def npz(rel: str, change: Any) -> Setup:
    """Rewrite an npz through ``change`` on its arrays (a dict, changed in place)."""

    def rewrite(data: bytes) -> bytes:
        with np.load(io.BytesIO(data), allow_pickle=False) as archive:
            arrays = {k: archive[k] for k in archive.files}
        change(arrays)
        out = io.BytesIO()
        np.savez_compressed(out, **arrays)
        return out.getvalue()

    return edit(rel, rewrite)


def near_empty_blocks(arrays: dict[str, Any]) -> None:
    """5,000 blocks of 4,096 cells, one known cell each (20 M cells to allocate)."""
    blocks = 5_000
    coords = np.zeros((blocks, 3), dtype=np.int64)
    coords[:, 0] = np.arange(blocks)
    known = np.zeros((blocks, 512), dtype=np.uint8)
    known[:, 0] = 1
    arrays.update(block_coords=coords, known=known, logodds=np.zeros(blocks))


def robots_renamed(doc: dict[str, Any]) -> dict[str, Any]:
    doc["robots"] = {"x" if k == "a" else "y": v for k, v in doc["robots"].items()}
    return doc


def pair_renamed(doc: dict[str, Any]) -> dict[str, Any]:
    doc["mutual_observations"][0]["pair"] = ["x0", "y1"]
    return doc


def station_beyond(doc: dict[str, Any]) -> dict[str, Any]:
    doc["global_localization"]["searches"][0]["station"] = "a99"
    return doc


def observation_beyond(doc: dict[str, Any]) -> dict[str, Any]:
    doc["mutual_observations"][0]["pair"] = ["a0", "b42"]
    return doc


def setting(key: str, value: Any) -> Any:
    def change(doc: dict[str, Any]) -> dict[str, Any]:
        doc[key] = value
        return doc

    return change


R = "report"
REPORT_CASES = [
    Case(R, "report.json truncated", EVALUATE, setup=(edit(REPORT, lambda b: b[: len(b) // 2]),),
         error=r"report\.json: not a coopmap report \(not JSON: "),
    Case(R, "report.json {}", EVALUATE, setup=(write(REPORT, "{}"),),
         error=r"report\.json: not a coopmap report: robots: required key is missing"),
    Case(R, "report.json a list", EVALUATE, setup=(write(REPORT, "[1, 2]"),),
         error=r"report\.json: not a coopmap report \(a list\)"),
    Case(R, "report.json a string", EVALUATE, setup=(write(REPORT, '"report"'),),
         error=r"report\.json: not a coopmap report \(a str\)"),
    Case(R, "report.json binary", EVALUATE, setup=(write(REPORT, bytes(range(256))),),
         error=r"report\.json: not UTF-8"),
    Case(R, "report.json empty", EVALUATE, setup=(write(REPORT, ""),),
         error=r"report\.json: not a coopmap report \(not JSON"),
    Case(R, "report.json nested 100000 deep", EVALUATE, setup=(write(REPORT, "[" * 100_000),),
         error=r"report\.json: not a coopmap report \(not JSON: nested too deeply\)"),
    Case(R, "report.json FIFO", EVALUATE, setup=(fifo(REPORT),),
         error=r"report\.json: not a regular file"),
    Case(R, "report.json missing", EVALUATE, setup=(remove(REPORT),),
         error=r"no result here \(report\.json missing\)"),
    Case(R, "report.json a directory", EVALUATE, setup=(directory(REPORT),),
         error=r"report\.json"),
    Case(R, "report.json of 600 MB", EVALUATE, setup=(sparse(REPORT, 600 * 2**20),),
         error=r"report\.json: 629,145,600 bytes, more than the", bomb=True),
    Case(R, "foreign robot names", EVALUATE, setup=(json_file(REPORT, robots_renamed),),
         error=r"report\.json: robots x, y are not the dataset's \(a, b\)"),
    Case(R, "robots uppercase", EVALUATE, setup=(json_file(REPORT, lambda d: {
        **d, "robots": {"A": d["robots"]["a"]}}),), error=r"not a coopmap report: robots\.A"),
    Case(R, "robots a list", EVALUATE, setup=(json_file(REPORT, setting("robots", ["a"])),),
         error=r"not a coopmap report: robots: "),
    Case(R, "observations a word", EVALUATE,
         setup=(json_file(REPORT, setting("observations", "many")),),
         error=r"not a coopmap report: observations: "),
    Case(R, "timings not numbers", EVALUATE,
         setup=(json_file(REPORT, setting("timings_s", {"total": "slow"})),),
         error=r"not a coopmap report: timings_s\.total: "),
    Case(R, "observation of foreign robots", EVALUATE, setup=(json_file(REPORT, pair_renamed),),
         error=r"report\.json names pose x0, which the dataset does not have"),
    Case(R, "observation of a pose the dataset lacks", EVALUATE,
         setup=(json_file(REPORT, observation_beyond),), error=r"names pose b42, which the dataset"),
    Case(R, "observation label malformed", EVALUATE, setup=(json_file(REPORT, lambda d: (
        d["mutual_observations"][0].update(pair=["a-1", "b0"]), d)[1]),),
        error=r"not a coopmap report: mutual_observations\[0\]\.pair\[0\]: String should match"),
    Case(R, "search station beyond the dataset", EVALUATE,
         setup=(json_file(REPORT, station_beyond),), error=r"names pose a99, which the dataset"),
    Case(R, "result folder a symlink", EVALUATE,
         setup=(lambda ws: (ws.result.rename(ws.tmp / "elsewhere"),
                            ws.result.symlink_to(ws.tmp / "elsewhere")),),
         error=r"result: is a symbolic link", keep=("elsewhere",)),
    Case(R, "--result missing", (*EVALUATE, "--result", "{tmp}/none"),
         error=r"none: no result here"),
    Case(R, "--result a file", (*EVALUATE, "--result", "{ds}/mission.yaml"),
         error=r"mission\.yaml: no result here"),
    Case(R, "--result the dataset", (*EVALUATE, "--result", "{ds}"), error=r"no result here"),
]  # fmt: skip


def _pickled(rel: str) -> Setup:
    def setup(ws: Workspace) -> None:
        path = Path(rel.format(**ws.fields()))
        with np.load(path) as archive:
            arrays = {k: archive[k] for k in archive.files}
        arrays["format"] = np.array([{"evil": 1}], dtype=object)
        np.savez_compressed(path, **arrays)

    return setup


def _bombed(source: Path, out: Path, member: str) -> Path:
    """``source`` (an npz) with ``member`` replaced by 512 MiB of zeros (a megabyte deflated)."""
    count = 2**26  # float64
    with zipfile.ZipFile(source) as src:
        kept = {n: src.read(n) for n in src.namelist() if n != member}
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED, compresslevel=1) as zf:
        for name, data in kept.items():
            zf.writestr(name, data)
        with zf.open(member, "w", force_zip64=True) as handle:
            header = {"descr": "<f8", "fortran_order": False, "shape": (count,)}
            np.lib.format.write_array_header_2_0(handle, header)  # type: ignore[arg-type]
            zeros = bytes(2**24)
            for _ in range(8 * count // len(zeros)):
                handle.write(zeros)
    return out


N = "map-npz"
MAP_CASES = [
    Case(N, "map.npz random bytes", EVALUATE,
         setup=(write(MAP, lambda: np.random.default_rng(2).bytes(50_000)),),
         error=r"map\.npz: not a readable coopmap map"),
    Case(N, "map.npz truncated", EVALUATE, setup=(edit(MAP, lambda b: b[: len(b) // 2]),),
         error=r"map\.npz: not a readable coopmap map"),
    Case(N, "map.npz empty", EVALUATE, setup=(write(MAP, b""),),
         error=r"map\.npz: not a readable coopmap map"),
    Case(N, "map.npz missing", EVALUATE, setup=(remove(MAP),), error=r"map\.npz: no such"),
    Case(N, "map.npz FIFO", EVALUATE, setup=(fifo(MAP),),
         error=r"map\.npz: not a regular file"),
    Case(N, "map.npz a directory", EVALUATE, setup=(directory(MAP),),
         error=r"map\.npz: is a directory"),
    Case(N, "map.npz logodds zip bomb", EVALUATE, setup=(copy("map_bomb.npz", MAP),),
         error=r"map\.npz: logodds declares 536,8\d\d,\d+ bytes, more than the", bomb=True),
    Case(N, "map.npz many near-empty blocks", EVALUATE, setup=(npz(MAP, near_empty_blocks),),
         error=r"map\.npz: 5,000 blocks of 4,096 cells hold only 5,000 known cells", bomb=True),
    Case(N, "map.npz without format", EVALUATE, setup=(npz(MAP, lambda a: a.pop("format")),),
         error=r"map\.npz: not a coopmap map \(no format/version entry\)"),
    Case(N, "map.npz version 3", EVALUATE,
         setup=(npz(MAP, lambda a: a.update(version=np.array(3))),),
         error=r"map\.npz: map format version 3 is not supported"),
    Case(N, "map.npz NaN log-odds", EVALUATE,
         setup=(npz(MAP, lambda a: a["logodds"].__setitem__(0, np.nan)),),
         error=r"map\.npz: logodds holds non-finite values"),
    Case(N, "map.npz log-odds beyond the clamps", EVALUATE,
         setup=(npz(MAP, lambda a: a["logodds"].__setitem__(0, 99.0)),),
         error=r"map\.npz: logodds outside the clamping bounds"),
    Case(N, "map.npz block_coords of 2 columns", EVALUATE,
         setup=(npz(MAP, lambda a: a.update(block_coords=a["block_coords"][:, :2])),),
         error=r"map\.npz: block_coords must be \(B, 3\) integers"),
    Case(N, "map.npz resolution 0", EVALUATE,
         setup=(npz(MAP, lambda a: a.update(resolution_m=np.array(0.0))),),
         error=r"map\.npz: .*resolution"),
    Case(N, "map.npz an object array", EVALUATE, setup=(_pickled(MAP),),
         error=r"map\.npz: not a readable coopmap map"),
    Case(N, "poses/a.tum NaN", EVALUATE, setup=(write(POSES, "0 nan 0 0 0 0 0 1\n"),),
         error=r"poses/a\.tum:1: TUM line: non-finite value"),
    Case(N, "poses/a.tum FIFO", EVALUATE, setup=(fifo(POSES),),
         error=r"poses/a\.tum: not a regular file"),
    Case(N, "poses/a.tum a directory", EVALUATE, setup=(directory(POSES),),
         error=r"poses/a\.tum: is a directory"),
    Case(N, "poses/a.tum empty", EVALUATE, setup=(write(POSES, ""),),
         error=r"poses/a\.tum: no poses"),
]  # fmt: skip


def checkpoint(change: Any) -> Setup:
    return npz(CHECKPOINT, change)


K = "checkpoint"
CHECKPOINT_CASES = [
    Case(K, "NaN poses", RESUME, setup=(checkpoint(lambda a: a["poses"].__setitem__(0, np.nan)),),
         error=r"checkpoint\.npz: checkpoint holds non-finite poses"),
    Case(K, "truncated", RESUME, setup=(edit(CHECKPOINT, lambda b: b[: len(b) // 2]),),
         error=r"checkpoint\.npz: not a readable checkpoint"),
    Case(K, "garbage", RESUME, setup=(write(CHECKPOINT, b"PK\x03\x04" + bytes(500)),),
         error=r"checkpoint\.npz: not a readable checkpoint"),
    Case(K, "missing", RESUME, setup=(remove(CHECKPOINT),),
         error=r"checkpoint\.npz: no checkpoint to resume from"),
    Case(K, "negative event count", RESUME,
         setup=(checkpoint(lambda a: a.update(events=np.array(-3))),),
         error=r"checkpoint\.npz: .*events"),
    Case(K, "more events than the stream", RESUME,
         setup=(checkpoint(lambda a: a.update(events=np.array(10**6))),),
         error=r"checkpoint holds 1000000 events but the stream has only \d+"),
    Case(K, "another graph", RESUME,
         setup=(checkpoint(lambda a: a.update(fingerprint=np.array("0" * 64))),),
         error=r"the event stream does not rebuild the checkpointed graph"),
    Case(K, "a zip bomb", RESUME, setup=(copy("checkpoint_bomb.npz", CHECKPOINT),),
         error=r"checkpoint\.npz: not a checkpoint: poses\.npy declares 536,8\d\d,\d+ bytes",
         bomb=True),
]  # fmt: skip

GUARDED = [
    Case(R, "report.json is /dev/zero", EVALUATE, guarded=True,
         setup=(symlink(REPORT, "/dev/zero"),), error=r"report\.json: not a regular file"),
    Case(N, "map.npz is /dev/zero", EVALUATE, guarded=True, setup=(symlink(MAP, "/dev/zero"),),
         error=r"map\.npz: not a regular file"),
    Case(N, "poses/a.tum is /dev/zero", EVALUATE, guarded=True,
         setup=(symlink(POSES, "/dev/zero"),), error=r"poses/a\.tum: not a regular file"),
]  # fmt: skip

CASES = REPORT_CASES + MAP_CASES + CHECKPOINT_CASES


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory, essex_simulated: Path) -> Path:
    """The dataset with its batch result and an iSAM2 checkpoint (a run cut short after 5
    events)."""
    from estimation.app.pipeline import run_isam

    ds = simulated_dataset(tmp_path_factory, essex_simulated)
    run_isam(ds, stop_after=5)
    assert (ds / ".result_isam.checkpoint.npz").is_file()
    return ds


@pytest.fixture(scope="module")
def bombs(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> dict[str, Path]:
    """The result's map and the checkpoint, each with one member swapped for a zip bomb."""
    folder = tmp_path_factory.mktemp("bombs")
    return {
        "map_bomb.npz": _bombed(dataset / "result" / "map.npz", folder / "map.npz", "logodds.npy"),
        "checkpoint_bomb.npz": _bombed(
            dataset / ".result_isam.checkpoint.npz", folder / "checkpoint.npz", "poses.npy"
        ),
    }


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Guarded:
    return run_guarded(GUARDED, tmp_path_factory.mktemp("guarded"), dataset)


@cases_param(CASES)
def test_a_damaged_result_is_one_line(
    case: Case, tmp_path: Path, dataset: Path, bombs: dict[str, Path]
) -> None:
    for name, path in bombs.items():
        (tmp_path / name).symlink_to(path)
    execute(case, workspace(case, tmp_path, dataset))


@cases_param(GUARDED)
def test_a_device_in_a_result_is_refused_unread(case: Case, guarded: Guarded) -> None:
    execute(case, guarded.workspaces[case.id], guarded.outcomes[case.id])


def test_the_bombs_are_bombs(bombs: dict[str, Path]) -> None:
    for path, member in zip(bombs.values(), ("logodds.npy", "poses.npy"), strict=True):
        with zipfile.ZipFile(path) as zf:
            assert zf.getinfo(member).file_size > 512 * 2**20
        assert path.stat().st_size < 4 * 2**20
