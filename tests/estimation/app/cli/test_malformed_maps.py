"""Family 4: damaged maps for localize (map_server YAML and PGM) and the OctoMap ``.bt`` that
evaluate-localization reads (``--only geb079 --data DIR``).

Each damage is one line naming the file, with memory bounded (a PGM header may declare
100,000 × 100,000 pixels, a ``.bt`` leaves of 2^45 cells).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.estimation.app.cli.malformed import (
    Case,
    Guarded,
    Setup,
    Workspace,
    cases_param,
    directory,
    edit,
    edit_text,
    execute,
    fifo,
    remove,
    run_guarded,
    symlink,
    workspace,
    write,
)

MAP_YAML, MAP_PGM = "{ds}/map.yaml", "{ds}/map.pgm"
SCAN_YAML = "{ds}/scan.yaml"
BT = "{ds}/data/octomap_fr079/geb079.bt"
LOCALIZE = ("localize", "--map", MAP_YAML, "--scan", SCAN_YAML)
GEB079 = ("evaluate-localization", "--only", "geb079", "--trials", "1", "--data", "{ds}/data")


def yaml_doc(text: str, rel: str = MAP_YAML) -> Setup:
    return write(rel, text)


def yaml_key(key: str, value: str | None, rel: str = MAP_YAML) -> Setup:
    """The map YAML with ``key`` set to ``value`` (YAML text), or removed when value is None."""

    def change(doc: str) -> str:
        data = yaml.safe_load(doc)
        data.pop(key, None)
        if value is not None:
            data[key] = yaml.safe_load(value)
        return yaml.safe_dump(data, default_flow_style=True)

    return edit_text(rel, change)


def drop_key(key: str) -> Setup:
    return yaml_key(key, None)


def pgm(header: bytes, pixels: bytes = b"") -> Setup:
    return write(MAP_PGM, header + pixels)


def sparse(rel: str, size: int) -> Setup:
    def setup(ws: Workspace) -> None:
        path = Path(rel.format(**ws.fields()))
        path.unlink()
        with path.open("wb") as handle:
            handle.truncate(size)

    return setup


def pixels_all(value: int) -> Setup:
    def change(data: bytes) -> bytes:
        head = data[: len(data) - 100 * 80]
        return head + bytes([value]) * (100 * 80)

    return edit(MAP_PGM, change)


Y = "map-yaml"
YAML_CASES = [
    Case(Y, "missing image", LOCALIZE, setup=(drop_key("image"),),
         error=r"map\.yaml: missing key 'image'"),
    Case(Y, "missing resolution", LOCALIZE, setup=(drop_key("resolution"),),
         error=r"map\.yaml: missing key 'resolution'"),
    Case(Y, "missing origin", LOCALIZE, setup=(drop_key("origin"),),
         error=r"map\.yaml: missing key 'origin'"),
    Case(Y, "resolution a word", LOCALIZE, setup=(yaml_key("resolution", "fine"),),
         error=r"map\.yaml: resolution must be a number, got 'fine'"),
    Case(Y, "resolution a boolean", LOCALIZE, setup=(yaml_key("resolution", "true"),),
         error=r"map\.yaml: resolution must be a number, got True"),
    Case(Y, "resolution 0", LOCALIZE, setup=(yaml_key("resolution", "0"),),
         error=r"map\.yaml: resolution must be positive"),
    Case(Y, "resolution negative", LOCALIZE, setup=(yaml_key("resolution", "-0.1"),),
         error=r"map\.yaml: resolution must be positive"),
    Case(Y, "resolution NaN", LOCALIZE, setup=(yaml_key("resolution", ".nan"),),
         error=r"map\.yaml: resolution must be a number, got nan"),
    Case(Y, "resolution a micrometre", LOCALIZE, setup=(yaml_key("resolution", "1.0e-6"),),
         error=r"map\.yaml: resolution|resolution.*differ"),
    Case(Y, "origin of two numbers", LOCALIZE, setup=(yaml_key("origin", "[0, 0]"),),
         error=r"map\.yaml: origin must be \[x, y, yaw\]"),
    Case(Y, "origin words", LOCALIZE, setup=(yaml_key("origin", "[a, b, c]"),),
         error=r"map\.yaml: origin must be \[x, y, yaw\]"),
    Case(Y, "origin NaN", LOCALIZE, setup=(yaml_key("origin", "[.nan, 0, 0]"),),
         error=r"map\.yaml: origin must be \[x, y, yaw\]"),
    Case(Y, "origin booleans", LOCALIZE, setup=(yaml_key("origin", "[true, 0, 0]"),),
         error=r"map\.yaml: origin must be \[x, y, yaw\]"),
    Case(Y, "origin a mapping", LOCALIZE, setup=(yaml_key("origin", "{x: 0}"),),
         error=r"map\.yaml: origin must be \[x, y, yaw\]"),
    Case(Y, "rotated origin", LOCALIZE, setup=(yaml_key("origin", "[0, 0, 0.5]"),),
         error=r"map\.yaml: a rotated map \(origin yaw 0\.5\) is not supported"),
    Case(Y, "negate 2", LOCALIZE, setup=(yaml_key("negate", "2"),),
         error=r"map\.yaml: negate must be 0 or 1, got 2"),
    Case(Y, "negate a word", LOCALIZE, setup=(yaml_key("negate", "yes please"),),
         error=r"map\.yaml: negate must be 0 or 1"),
    Case(Y, "negate true", LOCALIZE, setup=(yaml_key("negate", "true"),),
         error=r"map\.yaml: negate must be 0 or 1, got True"),
    Case(Y, "an alias", LOCALIZE, setup=(yaml_doc("o: &o [0, 0, 0]\nimage: map.pgm\n"
         "resolution: 0.1\norigin: *o\n"),), error=r"map\.yaml: .*aliases \(\*name\)"),
    Case(Y, "FIFO", LOCALIZE, setup=(fifo(MAP_YAML),), error=r"map\.yaml: not a regular file"),
    Case(Y, "a directory", LOCALIZE, setup=(directory(MAP_YAML),),
         error=r"map\.yaml: is a directory"),
    Case(Y, "missing", LOCALIZE, setup=(remove(MAP_YAML),), error=r"map\.yaml: no such file"),
    Case(Y, "a list", LOCALIZE, setup=(yaml_doc("- image\n"),),
         error=r"map\.yaml: a map description must be a YAML mapping"),
    Case(Y, "empty", LOCALIZE, setup=(yaml_doc(""),),
         error=r"map\.yaml: a map description must be a YAML mapping"),
    Case(Y, "binary", LOCALIZE, setup=(yaml_doc(bytes(range(256))),),  # type: ignore[arg-type]
         error=r"map\.yaml: not UTF-8"),
    Case(Y, "malformed YAML", LOCALIZE, setup=(yaml_doc("image: [\n"),),
         error=r"map\.yaml: malformed YAML"),
    Case(Y, "nested 20000 deep", LOCALIZE, setup=(yaml_doc("a: " + "[" * 20000),),
         error=r"map\.yaml: malformed YAML.*nested more than 100"),
    Case(Y, "image missing", LOCALIZE, setup=(yaml_key("image", "nothere.pgm"),),
         error=r"nothere\.pgm: no such file"),
    Case(Y, "image a directory", LOCALIZE, setup=(yaml_key("image", "."),),
         error=r"is a directory"),
    Case(Y, "image a list", LOCALIZE, setup=(yaml_key("image", "[a, b]"),),
         error=r"map\.yaml: image must be a file name"),
    Case(Y, "image empty", LOCALIZE, setup=(yaml_key("image", "''"),),
         error=r"map\.yaml: image must be a file name"),
    Case(Y, "image a FIFO", LOCALIZE, setup=(fifo(MAP_PGM),),
         error=r"map\.pgm: not a regular file"),
    Case(Y, "scan: rotated origin", LOCALIZE, setup=(yaml_key("origin", "[0, 0, 1]", SCAN_YAML),),
         error=r"scan\.yaml: a rotated map"),
    Case(Y, "scan: FIFO", LOCALIZE, setup=(fifo(SCAN_YAML),),
         error=r"scan\.yaml: not a regular file"),
    Case(Y, "scan: negate 2", LOCALIZE, setup=(yaml_key("negate", "2", SCAN_YAML),),
         error=r"scan\.yaml: negate must be 0 or 1"),
    Case(Y, "scan at another resolution", LOCALIZE,
         setup=(yaml_key("resolution", "0.05", SCAN_YAML),),
         error=r"resolution"),
    Case(Y, "--window-m without --prior", (*LOCALIZE, "--window-m", "3"),
         error=r"--window-m needs --prior"),
    Case(Y, "--window-m negative", (*LOCALIZE, "--prior", "1", "1", "0", "--window-m", "-3"),
         error=r"--window-m must be a positive number"),
    Case(Y, "--prior NaN", (*LOCALIZE, "--prior", "nan", "1", "0"),
         error=r"prior position must be finite, got \(nan, 1\.0\)"),
    Case(Y, "--pdf-out not a png", (*LOCALIZE, "--pdf-out", "{tmp}/pdf.txt"),
         error=r"pdf\.txt: --pdf-out must name a \.png file"),
    Case(Y, "a valid map with unknown keys", LOCALIZE, setup=(yaml_key("mode", "trinary"),
         yaml_key("comment", "'from ROS'")), ok=r"coopmap localize: x=2\.00\d m, y=2\.00\d m, .*, dominant"),
]  # fmt: skip

P = "pgm"
PGM_CASES = [
    Case(P, "not P5 (P2 text)", LOCALIZE, setup=(pgm(b"P2\n100 80\n255\n", b"1 " * 8000),),
         error=r"map\.pgm: not a binary PGM \(P5\) image"),
    Case(P, "P6 colour", LOCALIZE, setup=(pgm(b"P6\n100 80\n255\n", bytes(24000)),),
         error=r"map\.pgm: not a binary PGM"),
    Case(P, "width of 5000 digits", LOCALIZE, setup=(pgm(b"P5\n" + b"9" * 5000 + b" 80\n255\n"),),
         error=r"map\.pgm: PGM header number of 5000 digits"),
    Case(P, "maxval of 3000 digits", LOCALIZE, setup=(pgm(b"P5\n100 80\n" + b"1" * 3000 + b"\n"),),
         error=r"map\.pgm: PGM header number of 3000 digits"),
    Case(P, "maxval 65535", LOCALIZE, setup=(pgm(b"P5\n100 80\n65535\n", bytes(16000)),),
         error=r"map\.pgm: only 8-bit PGM \(maxval 255\) is supported, got maxval 65535"),
    Case(P, "maxval 0", LOCALIZE, setup=(pgm(b"P5\n100 80\n0\n", bytes(8000)),),
         error=r"map\.pgm: only 8-bit PGM"),
    Case(P, "zero size", LOCALIZE, setup=(pgm(b"P5\n0 0\n255\n"),),
         error=r"map\.pgm: empty image \(0 × 0\)"),
    Case(P, "zero height", LOCALIZE, setup=(pgm(b"P5\n100 0\n255\n"),),
         error=r"map\.pgm: empty image"),
    Case(P, "negative width", LOCALIZE, setup=(pgm(b"P5\n-100 80\n255\n", bytes(8000)),),
         error=r"map\.pgm: malformed PGM header"),
    Case(P, "truncated pixels", LOCALIZE, setup=(edit(MAP_PGM, lambda b: b[:-1000]),),
         error=r"map\.pgm: truncated: 100 × 80 pixels need 8000 bytes, found 7000"),
    Case(P, "huge declared dimensions, few bytes", LOCALIZE,
         setup=(pgm(b"P5\n100000 100000\n255\n", bytes(64)),), bomb=True,
         error=r"map\.pgm: truncated: 100000 × 100000 pixels need 10000000000 bytes, found 64"),
    Case(P, "a 2 GB file", LOCALIZE, setup=(sparse(MAP_PGM, 2**31),), bomb=True,
         error=r"map\.pgm: 2,147,483,648 bytes, more than the 1,073,741,824 expected"),
    Case(P, "random bytes", LOCALIZE,
         setup=(write(MAP_PGM, lambda: np.random.default_rng(4).bytes(5000)),),
         error=r"map\.pgm: not a binary PGM"),
    Case(P, "empty file", LOCALIZE, setup=(pgm(b""),), error=r"map\.pgm: not a binary PGM"),
    Case(P, "magic only", LOCALIZE, setup=(pgm(b"P5"),), error=r"map\.pgm: not a binary PGM"),
    Case(P, "a comment without end", LOCALIZE, setup=(pgm(b"P5\n# no end"),),
         error=r"map\.pgm: malformed PGM header"),
    Case(P, "no space after maxval", LOCALIZE, setup=(pgm(b"P5 100 80 255"),),
         error=r"map\.pgm: malformed PGM header"),
    Case(P, "a 1 × 1 map", LOCALIZE, setup=(pgm(b"P5\n1 1\n255\n", b"\x00"),),
         ok=r"coopmap localize: .*NOT dominant \(ambiguous\); 360 poses"),
    Case(P, "a map all unknown", LOCALIZE, setup=(pixels_all(205),),
         error=r"map grid has no known cell with occupied or free evidence"),
    Case(P, "a map all free", LOCALIZE, setup=(pixels_all(254),),
         ok=r"coopmap localize: .*NOT dominant"),
    Case(P, "a comment in the header", LOCALIZE, setup=(edit(MAP_PGM, lambda b: b.replace(
        b"P5\n", b"P5\n# a comment\n# another\n", 1)),), ok=r"coopmap localize: x=2\.00\d m, y=2\.00\d m, .*, dominant"),
]  # fmt: skip


def _occupied_only() -> Setup:
    def setup(ws: Workspace) -> None:
        from mapping.formats.octomap_bt import encode_bt

        cells = np.array([[i, j, 24] for i in range(20) for j in range(20)])
        Path(BT.format(**ws.fields())).write_bytes(encode_bt(cells, np.ones(len(cells)), 0.1))

    return setup


def bt_header(size: int, res: str = "0.1", tree_id: str = "OcTree") -> bytes:
    return f"# Octomap OcTree binary file\nid {tree_id}\nsize {size}\nres {res}\ndata\n".encode()


B = "octomap"
BT_CASES = [
    Case(B, "random bytes", GEB079, setup=(write(BT, lambda: np.random.default_rng(6).bytes(900)),),
         error=r"geb079\.bt: not an OctoMap binary file"),
    Case(B, "header without a data line", GEB079,
         setup=(write(BT, b"# Octomap OcTree binary file\nid OcTree\nsize 3\nres 0.1\n"),),
         error=r"geb079\.bt: truncated or malformed header \(no 'data' line\)"),
    Case(B, "header lacking res", GEB079,
         setup=(write(BT, b"# Octomap OcTree binary file\nid OcTree\nsize 3\ndata\n"),),
         error=r"geb079\.bt: header lacks id, size or res"),
    Case(B, "size a word", GEB079, setup=(edit(BT, lambda b: b.replace(b"size ", b"size x", 1)),),
         error=r"geb079\.bt: bad header value"),
    Case(B, "negative size", GEB079, setup=(write(BT, bt_header(-4)),),
         error=r"geb079\.bt: negative tree size -4"),
    Case(B, "size that disagrees", GEB079, setup=(edit(BT, lambda b: b.replace(b"size ", b"size 1",
         1)),), error=r"geb079\.bt: corrupt tree: the header says 1\d+ nodes"),
    Case(B, "truncated stream", GEB079, setup=(edit(BT, lambda b: b[: len(b) - 40]),),
         error=r"geb079\.bt: truncated: the tree needs more than"),
    Case(B, "resolution negative", GEB079, setup=(write(BT, bt_header(1, "-0.1") + bytes(2)),),
         error=r"geb079\.bt: resolution must be positive"),
    Case(B, "resolution NaN", GEB079, setup=(write(BT, bt_header(1, "nan") + bytes(2)),),
         error=r"geb079\.bt: resolution must be positive"),
    Case(B, "an empty tree", GEB079, setup=(write(BT, bt_header(0)),),
         error=r"geb079\.bt: no known voxel between 2\.3 and 2\.55 m \(the ceiling band\)"),
    Case(B, "a tree of unknown cells only", GEB079, setup=(write(BT, bt_header(1) + bytes(2)),),
         error=r"geb079\.bt: no known voxel between 2\.3 and 2\.55 m \(the ceiling band\)"),
    Case(B, "eight leaves of 2^45 cells", GEB079,
         setup=(write(BT, bt_header(9) + b"\xaa\xaa"),), bomb=True,
         error=r"the tree's leaves cover [\d,]+ cells, more than the 67,108,864"),
    Case(B, "occupied cells only", GEB079, setup=(_occupied_only(),),
         error=r"geb079\.bt: no known voxel between 0\.3 and 1\.5 m \(the floor band\)"),
    Case(B, "FIFO", GEB079, setup=(fifo(BT),), error=r"geb079\.bt: not a regular file"),
    Case(B, "a directory", GEB079, setup=(directory(BT),), error=r"geb079\.bt: is a directory"),
    Case(B, "a 2 GB file", GEB079, setup=(sparse(BT, 2**31),), bomb=True,
         error=r"geb079\.bt: 2,147,483,648 bytes, more than the"),
    Case(B, "missing: the part is skipped", GEB079, setup=(remove(BT),),
         ok=r"geb079: .*geb079\.bt not found"),
]  # fmt: skip

GUARDED = [
    Case(Y, "image is /dev/zero", LOCALIZE, guarded=True, setup=(yaml_key("image", "/dev/zero"),),
         error=r"/dev/zero: not a regular file"),
    Case(Y, "map yaml is /dev/zero", LOCALIZE, guarded=True, setup=(symlink(MAP_YAML, "/dev/zero"),),
         error=r"map\.yaml: not a regular file"),
    Case(B, "geb079.bt is /dev/zero", GEB079, guarded=True, setup=(symlink(BT, "/dev/zero"),),
         error=r"geb079\.bt: not a regular file"),
]  # fmt: skip

CASES = YAML_CASES + PGM_CASES + BT_CASES


def room_band(rows: int, cols: int) -> tuple[np.ndarray, np.ndarray]:
    """Occupancy and known cells of a room with walls and pillars (not symmetric)."""
    occupancy = np.zeros((rows, cols))
    known = np.zeros((rows, cols), dtype=bool)
    known[5:-5, 5:-5] = True
    occupancy[5:-5, 5] = occupancy[5:-5, -6] = occupancy[5, 5:-5] = occupancy[-6, 5:-5] = 1.0
    occupancy[20:24, 30:33] = occupancy[50:52, 60:70] = occupancy[12:40, 45] = 1.0
    return occupancy, known


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A 10 m × 8 m map, a local grid cut from it at (2 m, 2 m), and a small OctoMap building."""
    from mapping.band import Band
    from mapping.formats.octomap_bt import encode_bt
    from mapping.formats.pgm import write_band_pgm

    folder = tmp_path_factory.mktemp("maps")
    occupancy, known = room_band(80, 100)
    write_band_pgm(folder / "map.yaml", Band(occupancy, known, np.zeros(2), 0.1))
    crop = (slice(20, 60), slice(20, 60))
    write_band_pgm(folder / "scan.yaml", Band(occupancy[crop], known[crop], np.zeros(2), 0.1))
    cells, states = [], []
    for k in range(0, 27):  # floor to ceiling at 0.1 m: walls, free inside, a closed ceiling
        for i in range(40):
            for j in range(30):
                wall = i in (0, 39) or j in (0, 29) or (i == 20 and j < 15) or k >= 23
                cells.append((i, j, k))
                states.append(wall)
    bt = folder / "data" / "octomap_fr079" / "geb079.bt"
    bt.parent.mkdir(parents=True)
    bt.write_bytes(encode_bt(np.array(cells), np.array(states), 0.1))
    return folder


@pytest.fixture(scope="module")
def guarded(tmp_path_factory: pytest.TempPathFactory, dataset: Path) -> Guarded:
    return run_guarded(GUARDED, tmp_path_factory.mktemp("guarded"), dataset)


@cases_param(CASES)
def test_a_damaged_map_is_one_line(case: Case, tmp_path: Path, dataset: Path) -> None:
    execute(case, workspace(case, tmp_path, dataset))


@cases_param(GUARDED)
def test_a_device_as_a_map_is_refused_unread(case: Case, guarded: Guarded) -> None:
    execute(case, guarded.workspaces[case.id], guarded.outcomes[case.id])


def test_the_intact_maps_localize_and_the_intact_tree_is_searched(
    tmp_path: Path, dataset: Path
) -> None:
    case = Case(B, "intact", GEB079, ok=r"\| geb079")
    execute(case, workspace(case, tmp_path, dataset))
