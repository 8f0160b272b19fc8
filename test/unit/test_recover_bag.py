"""`recover_bag` renames and rewrites files, so it must touch only regular files inside the bag,
and must say so (exit 2, one line) rather than "0 messages recovered" when it finds nothing.
What a bag may cost is bounded before anything is done with it (aliases in metadata.yaml, what
a compressed file unpacks to, bags compressed per message refused), an interrupted recovery
leaves nothing behind, and a bag the system fails to read is never taken for an incomplete
one."""

from __future__ import annotations

import errno
import os
import resource
import signal
import stat
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest
import yaml
from rosbags.rosbag2 import CompressionFormat, CompressionMode, Writer
from rosbags.typesys import Stores, get_typestore

from constrained_diffusion_ros.recording import bags

try:
    from compression import zstd
except ImportError:  # Python < 3.14: rosbags' own dependency
    from backports import zstd

TYPESTORE = get_typestore(Stores.ROS2_JAZZY)
STRING = "std_msgs/msg/String"
REPO = Path(__file__).resolve().parents[2]
# A recover_bag run in its own process is held to these, so that a regression (a hang, a file
# that grows without bound) fails the test in seconds instead of hanging or filling CI.
RUN_TIMEOUT_S = 30
RUN_MEMORY = 1 << 30  # address space; the command needs about 150 MB
RUN_FILE_SIZE = 16 << 20  # largest file it may write


def killed_recording(directory: Path, messages: int) -> Path:
    """A bag as a recorder killed with SIGKILL leaves it: metadata.yaml from the start, the
    chunks flushed so far (one message each), no index, no footer. Returns its MCAP file."""
    writer = bags.open_bag(directory, {"trial_metadata": "{}"})
    connection = writer.add_connection("/pusher", STRING, typestore=TYPESTORE)
    bags.flush(writer)
    for step in range(messages):
        data = TYPESTORE.serialize_cdr(TYPESTORE.types[STRING](data=f"step {step}"), STRING)
        writer.write(connection, step + 1, data)
        bags.flush(writer)
    writer.storage.bio.close()  # killed: the summary and footer are never written
    return directory / f"{directory.name}.mcap"


def pointing_at(bag: Path, entry: str) -> Path:
    """A bag directory whose metadata.yaml lists `entry` as its one storage file."""
    bag.mkdir()
    no_time = {"nanoseconds_since_epoch": 0}
    information = {
        "version": bags.BAG_VERSION, "storage_identifier": "mcap", "relative_file_paths": [entry],
        "duration": {"nanoseconds": 0}, "starting_time": no_time, "message_count": 0,
        "topics_with_message_count": [], "compression_format": "", "compression_mode": "",
        "files": [{"path": entry, "starting_time": no_time, "duration": {"nanoseconds": 0},
                   "message_count": 0}],
        "custom_data": {}, "ros_distro": "rosbags"}
    (bag / "metadata.yaml").write_text(yaml.safe_dump({"rosbag2_bagfile_information":
                                                       information}))
    return bag


def with_storage(root: Path, write: Callable[[Path], None]) -> Path:
    """A killed recorder's bag whose MCAP file is replaced by what `write` makes at its path."""
    storage = killed_recording(root / "bag", 3)
    storage.unlink()
    write(storage)
    return root / "bag"


def edit_information(bag: Path, edit: Callable[[dict], None]) -> None:
    """Changes a bag's metadata.yaml through `edit(rosbag2_bagfile_information)`."""
    document = yaml.safe_load((bag / "metadata.yaml").read_text())
    edit(document["rosbag2_bagfile_information"])
    (bag / "metadata.yaml").write_text(yaml.safe_dump(document, sort_keys=False))


def non_text_custom_data(root: Path) -> Path:
    """A killed recorder's bag whose custom_data holds a list where text belongs."""
    bag = killed_recording(root / "bag", 3).parent
    edit_information(bag, lambda info: info["custom_data"].update(trial_metadata=[1, 2]))
    return bag


def outside_file(root: Path) -> Path:
    """Someone else's file, beside the bag: a killed recording that recovery would accept."""
    return killed_recording(root / "outside", 3)


ATTACKS: dict[str, Callable[[Path], tuple[Path, str]]] = {
    "absolute path": lambda root: (pointing_at(root / "bag", str(outside_file(root))),
                                   "outside.mcap"),
    "dotdot path": lambda root: (
        pointing_at(root / "bag", f"../outside/{outside_file(root).name}"), "../outside"),
    "symlink out": lambda root: (
        with_storage(root, lambda path: path.symlink_to(outside_file(root))), "links outside"),
    "fifo": lambda root: (with_storage(root, os.mkfifo), "not a regular file"),
    "garbage": lambda root: (
        with_storage(root, lambda path: path.write_bytes(bytes(range(256)) * 16)),
        "not an MCAP file"),
    "empty file": lambda root: (
        with_storage(root, lambda path: path.write_bytes(b"")), "empty"),
    "mcap without messages": lambda root: (killed_recording(root / "bag", 0).parent,
                                           "no complete message"),
    # issue 41, finding 6.3: rosbags' reader raised TypeError from ord(b"") on this file
    "mcap magic only": lambda root: (
        with_storage(root, lambda path: path.write_bytes(bags.MCAP_MAGIC)),
        "not a complete MCAP file"),
    "custom_data not text": lambda root: (non_text_custom_data(root), "custom_data"),
}


def tree(root: Path) -> dict[str, tuple]:
    """Every path under root, what it is and what it holds: read without following a symlink
    and without opening a FIFO."""
    found: dict[str, tuple] = {}
    for directory, names, files in os.walk(root):
        for name in names + files:
            path = Path(directory, name)
            mode = os.lstat(path).st_mode
            if stat.S_ISLNK(mode):
                found[str(path.relative_to(root))] = ("link", os.readlink(path))
            elif stat.S_ISREG(mode):
                found[str(path.relative_to(root))] = ("file", path.read_bytes())
            else:
                found[str(path.relative_to(root))] = (stat.S_IFMT(mode),)
    return found


@contextmanager
def unblocking(root: Path) -> Iterator[list[Path]]:
    """Opens the write end of every FIFO under root whenever something waits to read it, so
    that code which opens one gets end-of-file instead of hanging the test. Yields the FIFOs
    it had to answer: a reader that never opens them leaves the list empty."""
    fifos = [path for path in root.rglob("*") if stat.S_ISFIFO(os.lstat(path).st_mode)]
    answered: list[Path] = []
    stop = threading.Event()

    def answer() -> None:
        while not stop.wait(0.02):
            for fifo in fifos:
                try:
                    os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
                except OSError:  # nobody is reading it (ENXIO), or it was renamed
                    continue
                answered.append(fifo)

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        yield answered
    finally:
        stop.set()
        thread.join()


@pytest.mark.parametrize("attack", list(ATTACKS))
def test_recover_bag_refuses_and_changes_nothing(attack, tmp_path, capsys):
    bag, named = ATTACKS[attack](tmp_path)
    before = tree(tmp_path)
    capsys.readouterr()
    with unblocking(tmp_path) as opened_fifos:
        code = bags.main([str(bag)])
    out, err = capsys.readouterr()
    assert code == 2, (out, err)
    assert out == ""
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("recover_bag: error: "), err
    assert named in lines[0], lines[0]
    assert opened_fifos == []
    assert tree(tmp_path) == before  # nothing renamed, written or left behind, in or out


@pytest.mark.parametrize(("cut", "kept"), [("inside the last chunk", 4),
                                           ("one byte short", 5)])
def test_recover_bag_still_indexes_a_cut_off_recording(cut, kept, tmp_path, capsys):
    """A killed recorder's file, cut off in mid-write (inside its last chunk, or inside the
    message index after it: mcap then raises struct.error): the complete messages are
    recovered, the original kept as .unindexed, and a second run leaves the bag alone."""
    four = killed_recording(tmp_path / "four", 4).stat().st_size
    storage = killed_recording(tmp_path / "bag", 5)
    five = storage.stat().st_size
    data = storage.read_bytes()[:(four + five) // 2 if cut == "inside the last chunk" else -1]
    storage.write_bytes(data)
    assert bags.main([str(tmp_path / "bag")]) == 0
    messages = bags.read_messages(tmp_path / "bag")
    assert [m.data for m in messages["/pusher"]] == [f"step {step}" for step in range(kept)]
    assert (tmp_path / "bag" / "bag.mcap.unindexed").read_bytes() == data
    assert sorted(p.name for p in (tmp_path / "bag").iterdir()) == [
        "bag.mcap", "bag.mcap.unindexed", "metadata.yaml"]
    assert f"{kept} messages recovered" in capsys.readouterr().out
    assert bags.main([str(tmp_path / "bag")]) == 0
    assert "complete already" in capsys.readouterr().out


def in_process_of_its_own(code: str, bag: Path, tmp: Path) -> subprocess.CompletedProcess:
    """Python `code` run with BAG as its argument in a fresh process with `tmp` as its
    $TMPDIR, bounded in time, memory and file size (RUN_*). A run past the time limit fails
    the test."""

    def limits() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (RUN_MEMORY, RUN_MEMORY))
        resource.setrlimit(resource.RLIMIT_FSIZE, (RUN_FILE_SIZE, RUN_FILE_SIZE))

    env = dict(os.environ, TMPDIR=str(tmp), OMP_NUM_THREADS="1",
               PYTHONPATH=os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]))
    try:
        return subprocess.run([sys.executable, "-c", code, str(bag)], cwd=REPO, env=env,
                              preexec_fn=limits, capture_output=True, text=True,
                              timeout=RUN_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        pytest.fail(f"the command still ran after {RUN_TIMEOUT_S} s")


def recover_in_process_of_its_own(bag: Path, tmp: Path, prelude: str = ""
                                  ) -> subprocess.CompletedProcess:
    """`recover_bag BAG` run by `in_process_of_its_own`; `prelude` runs before it."""
    code = (f"import sys\n{prelude}\n"
            "from constrained_diffusion_ros.recording import bags\n"
            "sys.exit(bags.main(sys.argv[1:]))\n")
    return in_process_of_its_own(code, bag, tmp)


def assert_refused(result: subprocess.CompletedProcess, named: str) -> None:
    """Exit 2 and one line on stderr naming `named`, nothing on stdout."""
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert result.stdout == ""
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and lines[0].startswith("recover_bag: error: "), lines[-20:]
    assert named in lines[0], lines[0]


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    """A flow sequence of nested anchors, each level `width` aliases of the one before: a few
    hundred bytes, width**levels leaves once expanded (387 million for nine of nine)."""
    parts = ["&a0 [" + ", ".join(["lol"] * width) + "]"]
    parts += [f"&a{level} [" + ", ".join([f"*a{level - 1}"] * width) + "]"
              for level in range(1, levels + 1)]
    return "[" + ", ".join(parts) + "]"


def test_recover_bag_refuses_an_alias_bomb_in_metadata_at_once(tmp_path):
    """Issue 41, finding 6.1: metadata.yaml with a billion-laughs custom_data value (read with
    plain yaml.safe_load, then printed whole by rosbags' writer) made recover_bag run for ever,
    growing 25 MB/s, and a kill left its .recovering-* scratch behind. The bounded YAML reader
    refuses it before anything is written."""
    bag = killed_recording(tmp_path / "bag", 3).parent
    metadata = bag / "metadata.yaml"
    text = metadata.read_text()
    assert text.count("  custom_data:\n") == 1
    metadata.write_text(text.replace("  custom_data:\n",
                                     f"  custom_data:\n    bomb: {alias_bomb()}\n"))
    custom = yaml.safe_load(metadata.read_text())["rosbag2_bagfile_information"]["custom_data"]
    assert next(iter(custom)) == "bomb" and len(custom["bomb"][9][0][0][0]) == 9  # the bomb is in
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = recover_in_process_of_its_own(bag, tmp_path / "tmp")
    assert_refused(result, "alias bomb")
    assert tree(tmp_path) == before  # no .recovering-* left, the bag unchanged


def file_compressed(bag: Path, storage: bytes) -> Path:
    """A killed recorder's bag turned into one compressed per file, its storage `storage`."""
    (killed_recording(bag, 3)).unlink()

    def compressed(info: dict) -> None:
        info.update(compression_format="zstd", compression_mode="FILE",
                    relative_file_paths=[f"{bag.name}.mcap.zstd"])
        info["files"][0]["path"] = f"{bag.name}.mcap.zstd"

    edit_information(bag, compressed)
    (bag / f"{bag.name}.mcap.zstd").write_bytes(storage)
    return bag


def test_recover_bag_refuses_a_decompression_bomb_without_writing_it(tmp_path):
    """Issue 41, finding 6.2: a bag compressed per file (72 kB of zstd) made rosbags' reader
    unpack 2 GiB into $TMPDIR before recover_bag gave up. Here 128 MiB of zeros in about 6 kB,
    more than the limit (64 MiB for so small a file): refused in one line, $TMPDIR left empty,
    and the run is held to 16 MiB per file written, so the old behaviour fails fast."""
    frame = zstd.compress(bytes(1 << 20))
    unpacks_to = 128 << 20
    assert unpacks_to > max(64 << 20, 64 * len(frame) * 128)  # the limit, as --help states it
    bag = file_compressed(tmp_path / "bag", frame * (unpacks_to >> 20))
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = recover_in_process_of_its_own(bag, tmp_path / "tmp")
    assert_refused(result, "unpack to more than")
    assert list((tmp_path / "tmp").iterdir()) == []
    assert tree(tmp_path) == before


def complete_bag(bag: Path, compression: CompressionMode | None = None,
                 stored: list[bytes] | None = None) -> Path:
    """A closed bag of /pusher messages "step 0" to "step 2" (or of `stored`, the bytes as
    they are), compressed with zstd as `compression` says."""
    writer = Writer(bag, version=bags.BAG_VERSION, storage_plugin=bags.StoragePlugin.MCAP)
    if compression is not None:
        writer.set_compression(compression, CompressionFormat.ZSTD)
    writer.open()
    connection = writer.add_connection("/pusher", STRING, typestore=TYPESTORE)
    if stored is None:
        stored = [TYPESTORE.serialize_cdr(TYPESTORE.types[STRING](data=f"step {step}"), STRING)
                  for step in range(3)]
    for step, data in enumerate(stored):
        writer.write(connection, step + 1, data)
    writer.close()
    return bag


def test_recover_bag_leaves_a_complete_compressed_bag_alone(tmp_path, capsys):
    """The limit does not stop an honest bag compressed per file: it is found complete, and
    read back."""
    complete_bag(tmp_path / "bag", CompressionMode.FILE)
    information = yaml.safe_load((tmp_path / "bag" / "metadata.yaml").read_text())
    assert information["rosbag2_bagfile_information"]["compression_mode"].lower() == "file"
    before = tree(tmp_path)
    assert bags.main([str(tmp_path / "bag")]) == 0
    assert "complete already" in capsys.readouterr().out
    assert tree(tmp_path) == before
    assert [m.data for m in bags.read_messages(tmp_path / "bag")["/pusher"]] == [
        "step 0", "step 1", "step 2"]


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP, signal.SIGINT])
def test_an_interrupted_recovery_leaves_the_bag_as_it_was(signum, tmp_path):
    """Issue 41, finding 6.1: a recovery stopped by a signal in mid-write removes its
    .recovering-* scratch and renames nothing. The process signals itself after the first
    message is copied; it must end (not finish the recovery) with the bag unchanged."""
    bag = killed_recording(tmp_path / "bag", 3).parent
    # Started under nohup, or in the background of a shell, the test inherits SIGHUP or
    # SIGINT ignored, and recover_bag (rightly) leaves an ignored signal ignored: handled
    # here as in a process started from a terminal.
    default = "signal.default_int_handler" if signum == signal.SIGINT else "signal.SIG_DFL"
    prelude = (
        "import os, signal, time\n"
        f"signal.signal({int(signum)}, {default})\n"
        "from constrained_diffusion_ros.recording import bags\n"
        "complete = bags._complete_messages\n"
        "def interrupted(stream):\n"
        "    for index, record in enumerate(complete(stream)):\n"
        "        if index == 1:\n"
        f"            os.kill(os.getpid(), {int(signum)})\n"
        "            time.sleep(10)\n"
        "            print('not interrupted')\n"
        "        yield record\n"
        "bags._complete_messages = interrupted\n")
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = recover_in_process_of_its_own(bag, tmp_path / "tmp", prelude)
    assert result.returncode in (128 + signum, -signum), (result.returncode, result.stderr)
    assert "not interrupted" not in result.stdout
    assert tree(tmp_path) == before


def test_read_messages_names_a_file_that_is_not_a_whole_mcap(tmp_path):
    """Issue 41, finding 6.3, for the readers of bags: a storage file of only the MCAP magic
    is a one-line ValueError pointing at recover_bag, not a TypeError from rosbags' parser."""
    bag = with_storage(tmp_path, lambda path: path.write_bytes(bags.MCAP_MAGIC))
    with pytest.raises(ValueError, match=r"not a closed bag .*recover_bag"):
        bags.read_messages(bag)


def message_bomb(bag: Path) -> Path:
    """A closed bag whose one message is stored as 4 GiB of zeros in 200 kB of zstd (4096
    frames of 1 MiB each), marked compressed per message (zstd): rosbags' reader unpacks each
    message with zstd.decompress, whole, whatever its size."""
    complete_bag(bag, stored=[zstd.compress(bytes(1 << 20)) * 4096])
    edit_information(bag, lambda info: info.update(compression_format="zstd",
                                                   compression_mode="message"))
    return bag


def test_read_messages_refuses_a_bag_compressed_per_message(tmp_path):
    """Review of issue 41, finding 6.2: the decompression bomb, compressed per message instead
    of per file, went past the limit and unpacked in memory when the bag was read (here: past
    the 1 GiB the process may use, a MemoryError). A bag compressed per message is refused in
    one ValueError line before a message is read."""
    bag = message_bomb(tmp_path / "bag")
    code = ("import sys\n"
            "from constrained_diffusion_ros.recording import bags\n"
            "try:\n"
            "    bags.read_messages(sys.argv[1])\n"
            "except ValueError as error:\n"
            "    print(error)\n"
            "    sys.exit(2)\n"
            "print('read')\n")
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = in_process_of_its_own(code, bag, tmp_path / "tmp")
    assert result.returncode == 2, (result.returncode, result.stderr[-2000:])
    assert result.stdout.splitlines() == [f"{bag}: {bags.MESSAGE_MODE_REFUSED}"]
    assert tree(tmp_path) == before


def test_recover_bag_refuses_a_bag_compressed_per_message(tmp_path):
    """The command says so too, in one line (and in --help), rather than "complete already" of
    a bag that nothing here will read."""
    bag = message_bomb(tmp_path / "bag")
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = recover_in_process_of_its_own(bag, tmp_path / "tmp")
    assert_refused(result, "compressed per message (compression_mode: message)")
    assert tree(tmp_path) == before
    usage = in_process_of_its_own(
        "from constrained_diffusion_ros.recording import bags\nbags.main(['--help'])\n",
        bag, tmp_path / "tmp").stdout
    assert "compression_mode: message" in " ".join(usage.split())


def test_read_messages_asks_rosbags_what_compression_it_reads(tmp_path, monkeypatch):
    """Were metadata.yaml read otherwise by the package than by rosbags, rosbags' own view of
    an honest bag compressed per message still has it refused, before a message is read."""
    bag = complete_bag(tmp_path / "bag", CompressionMode.MESSAGE)
    assert bags.compression_mode(bags.bag_information(bag)) == "message"
    monkeypatch.setattr(bags, "compression_mode", lambda information: "")
    with pytest.raises(ValueError, match="compression_mode: message"):
        bags.read_messages(bag)


def denied_storage() -> str:
    """Prelude: opening a .mcap file fails as when its permissions deny it (the tests run as
    root, whom chmod does not stop). rosbags raises ReaderError from the PermissionError."""
    return ("import errno, pathlib\n"
            "real_open = pathlib.Path.open\n"
            "def denied(self, *args, **kwargs):\n"
            "    if self.suffix == '.mcap':\n"
            "        raise PermissionError(errno.EACCES, 'Permission denied', str(self))\n"
            "    return real_open(self, *args, **kwargs)\n"
            "pathlib.Path.open = denied\n")


def failing_disk() -> str:
    """Prelude: reading a storage file fails with EIO, as on a failing disk, after it opened
    (rosbags raises the OSError as it is); the package's own reader of MCAP records still
    reads it, so a recovery would go through."""
    return ("import errno\n"
            "from rosbags.rosbag2 import storage_mcap\n"
            "def failing(self):\n"
            "    raise OSError(errno.EIO, 'Input/output error')\n"
            "storage_mcap.McapReader._open = failing\n")


@pytest.mark.parametrize(("fault", "named"), [(denied_storage, "Permission denied"),
                                              (failing_disk, "Input/output error")])
def test_recover_bag_reports_a_bag_it_cannot_read_and_recovers_nothing(fault, named, tmp_path):
    """Review of issue 41, finding 6: OSError was among the faults of an incomplete bag, so a
    complete bag the system failed to read (permission denied, an I/O error) was "recovered":
    rewritten with a custom_data saying its recorder had died. Now one line naming the error,
    exit 2, no recovery attempted and nothing changed."""
    bag = complete_bag(tmp_path / "bag")
    prelude = (fault() +
               "from constrained_diffusion_ros.recording import bags\n"
               "rewrite = bags._rewrite\n"
               "def attempted(*args):\n"
               "    print('recovery attempted')\n"
               "    return rewrite(*args)\n"
               "bags._rewrite = attempted\n")
    (tmp_path / "tmp").mkdir()
    before = tree(tmp_path)
    result = recover_in_process_of_its_own(bag, tmp_path / "tmp", prelude)
    assert_refused(result, named)  # and nothing on stdout: no recovery attempted
    assert "not recovered" in result.stderr
    assert tree(tmp_path) == before


def test_read_messages_says_a_bag_cannot_be_read_rather_than_not_closed(tmp_path, monkeypatch):
    """The readers of bags do not send a bag the system fails to read to recover_bag."""
    from rosbags.rosbag2 import storage_mcap

    def failing(_self: object) -> None:
        raise OSError(errno.EIO, "Input/output error")

    bag = complete_bag(tmp_path / "bag")
    monkeypatch.setattr(storage_mcap.McapReader, "_open", failing)
    with pytest.raises(ValueError, match=r"cannot be read \(\[Errno 5\] Input/output error\)$"):
        bags.read_messages(bag)
