"""Trial bags (rosbag2 directories, MCAP storage): read back with rosbags (no ROS needed), kept
readable when the recorder is killed, and recovered after such a kill.

rosbags' MCAP writer keeps up to 1 MiB of messages in memory and writes the summary, the index
and metadata.yaml only when the bag is closed: a recorder killed with SIGKILL left 0 bytes. So the
recorder writes metadata.yaml when it opens the bag and hands every pending chunk to the operating
system twice a second (`flush`); after a kill, `recover_bag DIR` (`recover`) reads the complete
records the file holds and rewrites the bag with its index and metadata.
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import shutil
import signal
import stat
import struct
import sys
import tempfile
import threading
from collections import Counter, defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path, PurePath

import yaml
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader
from rosbags.rosbag2 import Reader, ReaderError, StoragePlugin, Writer
from rosbags.rosbag2.metadata import parse_qos
from rosbags.typesys import Stores, get_typestore

from constrained_diffusion_ros.cli import ArgumentParser, run_command
from constrained_diffusion_ros.planning.constraint_configs import read_yaml
from msg_schemas import TOPICS, Endpoint
from msg_schemas.conversions import step_of_stamp
from sim_bridge import CONTROL_HZ

try:  # the zstd rosbags decompresses with
    from compression import zstd
except ImportError:  # Python < 3.14
    from backports import zstd

BAG_VERSION = 9  # rosbag2 metadata version written by ROS 2 Jazzy
FLUSH_PERIOD_S = 0.5  # a SIGKILL loses at most about this much of the recording
RECORDER_STATE = "recorder"  # custom_data key while a bag is open, and after a recovery
MCAP_MAGIC = b"\x89MCAP0\r\n"  # how every MCAP file starts
TRIAL_TOPICS = {"pusher": "pusher", "block": "block_pose",
                "setpoint": "setpoint"}
# A bag compressed per file (compression_mode: file) is unpacked whole into $TMPDIR by rosbags'
# Reader before a message is read; zstd on ROS messages packs 3-10 times, a crafted file some
# 30000 times (72 kB -> 2 GiB). So what the files of a bag unpack to is counted first, without
# writing, and the bag is refused past this many times their size (but 64 MiB always pass).
MAX_UNPACK_RATIO = 64
MIN_UNPACK_LIMIT = 64 << 20
# A bag compressed per message (compression_mode: message) has each message unpacked by rosbags
# with no limit at all (a few kB of zstd -> GiB in memory), and no recorder of this package
# writes one: such bags are refused, by every reader of bags here and by recover_bag.
MESSAGE_MODE_REFUSED = ("compressed per message (compression_mode: message), which rosbags "
                        "unpacks without a limit; refused (bags uncompressed or compressed per "
                        "file are read)")
# What rosbags' and mcap's parsers raise on bytes that are not a whole MCAP file, besides their
# own errors (a file of only the magic gives TypeError from ord(b""), one cut in a fixed-size
# field struct.error, one shorter than a footer OSError EINVAL from its seek). Any other OSError
# (permission, I/O error) is the system failing to read the bag, not a fault of the bag:
# `_read_error` tells them apart.
STORAGE_FAULTS = (ReaderError, McapError, EOFError, struct.error, TypeError, ValueError,
                  AssertionError, IndexError, KeyError, OSError)


def read_messages(bag: str | Path) -> dict[str, list]:
    """Every message of a bag, deserialised, in recording order, per topic."""
    return by_topic(read_timed_messages(bag))


def by_topic(timed: list[tuple[int, str, object]]) -> dict[str, list]:
    """`read_timed_messages`' messages per topic, in recording order."""
    messages: dict[str, list] = defaultdict(list)
    for _time_ns, topic, message in timed:
        messages[topic].append(message)
    return dict(messages)


def read_timed_messages(bag: str | Path) -> list[tuple[int, str, object]]:
    """(record time in ns, topic, message) of every message of a bag, in recording order. A bag
    that cannot be used is one ValueError line: not closed, compressed per message
    (MESSAGE_MODE_REFUSED) or past the unpacking limit, or not readable by the system."""
    typestore = get_typestore(Stores.ROS2_JAZZY)
    bag = Path(bag)
    check_unpacked_size(bag, bag_information(bag))  # before rosbags reads or unpacks anything
    try:
        with Reader(bag) as reader:
            per_message = reader.compression_mode == "message"  # as rosbags read metadata.yaml
            raws = [] if per_message else [(timestamp, connection.topic, connection.msgtype, raw)
                                           for connection, timestamp, raw in reader.messages()]
    except STORAGE_FAULTS as error:
        if (failure := _read_error(error)) is not None:
            # a ValueError still, as callers (a trial drawing its figures) take one for a bag
            # they cannot use; but not called unclosed, nor sent to recover_bag
            raise ValueError(f"{bag}: cannot be read ({failure})") from failure
        raise ValueError(f"{bag}: not a closed bag ({type(error).__name__}: {error}); if its "
                         f"recorder died, run `recover_bag {bag}`") from None
    if per_message:
        raise ValueError(f"{bag}: {MESSAGE_MODE_REFUSED}")
    return [(timestamp, topic, typestore.deserialize_cdr(raw, msgtype))
            for timestamp, topic, msgtype, raw in raws]


def messages_of(messages: dict[str, list], endpoint: Endpoint) -> list:
    """The messages of a contract topic in a bag recorded in any namespace: the default one's
    if present, else the only topic of that name; a bag of several robots has to be asked by
    full name."""
    if endpoint.resolved() in messages:
        return messages[endpoint.resolved()]
    found = [topic for topic in messages if topic.rsplit("/", 1)[-1] == endpoint.name]
    if len(found) > 1:
        raise ValueError(f"the bag has {endpoint.name!r} in several namespaces: {found}")
    return messages[found[0]] if found else []


def read_trial(bag: str | Path) -> dict[str, dict[int, object]]:
    """Pusher, block pose and setpoint messages keyed by control step (from header stamps)."""
    return trial_steps(read_messages(bag))


def read_unfinished(bag: Path) -> dict[str, list]:
    """The messages a bag still being recorded holds so far (what the recorder has handed to
    the operating system: up to FLUSH_PERIOD_S behind), deserialised, per topic: a trial checks
    its bag with it before it stops the nodes."""
    files = bag_information(bag).get("relative_file_paths") or []
    typestore = get_typestore(Stores.ROS2_JAZZY)
    messages: dict[str, list] = defaultdict(list)
    try:
        with (bag / files[0]).open("rb") as stream:
            for schema, channel, message in _complete_messages(stream):
                messages[channel.topic].append(typestore.deserialize_cdr(message.data,
                                                                         schema.name))
    except (IndexError, FileNotFoundError):
        pass  # no storage file yet
    return dict(messages)


def trial_steps(messages: dict[str, list]) -> dict[str, dict[int, object]]:
    """The trial topics' messages of a bag (`read_messages`), keyed by control step."""
    trial: dict[str, dict[int, object]] = {}
    for kind, topic in TRIAL_TOPICS.items():
        trial[kind] = {}
        for msg in messages_of(messages, TOPICS[topic]):
            trial[kind][step_of_stamp(msg.header.stamp, CONTROL_HZ)] = msg
    return trial


def open_bag(directory: Path, custom_data: dict[str, str]) -> Writer:
    """A new MCAP bag whose metadata.yaml is valid from the start (no messages yet): a reader
    told to open it after a crash is pointed at `recover_bag` rather than at a missing file."""
    writer = Writer(directory, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
    writer.open()  # raises WriterError if the directory exists
    for key, value in custom_data.items():
        writer.set_custom_data(key, value)
    mcap_name = f"{directory.name}.mcap"  # the name rosbags gives the storage file
    no_time = {"nanoseconds_since_epoch": 0}
    state = (f"recording; if the recorder died, run `recover_bag {directory}` to index what it "
             f"wrote")
    information = {
        "version": BAG_VERSION, "storage_identifier": "mcap", "relative_file_paths": [mcap_name],
        "duration": {"nanoseconds": 0}, "starting_time": no_time, "message_count": 0,
        "topics_with_message_count": [], "compression_format": "", "compression_mode": "",
        "files": [{"path": mcap_name, "starting_time": no_time, "duration": {"nanoseconds": 0},
                   "message_count": 0}],
        "custom_data": {**custom_data, RECORDER_STATE: state}, "ros_distro": "rosbags"}
    (directory / "metadata.yaml").write_text(
        yaml.safe_dump({"rosbag2_bagfile_information": information}, sort_keys=False))
    return writer


def flush(writer: Writer) -> None:
    """Write the pending chunk and hand it to the operating system, so that a SIGKILL loses only
    what came after. rosbags has no flush of its own: this reaches into its MCAP storage writer
    (rosbags is pinned; test_recorder kills a recorder to check this still holds)."""
    storage = writer.storage
    if storage is None:
        return
    if storage.chunk.bio.tell():
        storage.close_chunk()
    storage.bio.flush()


def bag_information(bag: Path) -> dict:
    """The `rosbag2_bagfile_information` of a bag directory's metadata.yaml, read by the
    package's bounded YAML reader (`read_yaml`: a regular file of bounded size, aliases
    bounded, so a billion-laughs file is refused at once)."""
    path = bag / "metadata.yaml"
    if not (path.is_symlink() or path.exists()):
        raise ValueError(f"{bag} is not a rosbag2 directory (no metadata.yaml)")
    try:
        document = read_yaml(path)
    except ValueError as error:  # "PATH: not valid YAML ...", or a file that is not regular
        named = f"{path}: "
        if not str(error).startswith(named):
            raise
        raise ValueError(f"{path} is not rosbag2 metadata: {str(error)[len(named):]}") from None
    information = (document.get("rosbag2_bagfile_information")
                   if isinstance(document, dict) else None)
    if not isinstance(information, dict):
        raise ValueError(f"{path} is not rosbag2 metadata: no rosbag2_bagfile_information "
                         f"mapping")
    return information


def compression_mode(information: dict) -> str:
    """A bag's compression mode as rosbags reads it: "" (none), "file" or "message"."""
    mode = str(information.get("compression_mode") or "").lower()
    return "" if mode == "none" else mode


def check_unpacked_size(bag: Path, information: dict) -> None:
    """Refuses (one ValueError line) a bag compressed per message (MESSAGE_MODE_REFUSED), and
    one compressed per file whose files would unpack to more than MAX_UNPACK_RATIO times their
    size (at least MIN_UNPACK_LIMIT): rosbags' Reader unpacks them whole into $TMPDIR on
    opening. Counted by decompressing without writing, and no further than the limit. Any
    other bag passes untouched."""
    mode = compression_mode(information)
    if mode == "message":
        raise ValueError(f"{bag}: {MESSAGE_MODE_REFUSED}")
    if mode != "file":
        return
    files = information.get("relative_file_paths") or []
    if not isinstance(files, list):
        raise ValueError(f"{bag / 'metadata.yaml'}: relative_file_paths is not a list")
    sources = [_file_in_bag(bag, entry) for entry in files]
    limit = max(MIN_UNPACK_LIMIT, MAX_UNPACK_RATIO * sum(s.stat().st_size for s in sources))
    unpacked = 0
    for source in sources:
        try:
            with source.open("rb") as raw, zstd.open(raw, "rb") as stream:
                while piece := stream.read(min(1 << 20, limit - unpacked + 1)):
                    unpacked += len(piece)
                    if unpacked > limit:
                        raise ValueError(
                            f"{bag}: its compressed files unpack to more than {limit} bytes "
                            f"(the limit: {MAX_UNPACK_RATIO} times their size, at least "
                            f"{MIN_UNPACK_LIMIT >> 20} MiB); refused, nothing written")
        except (zstd.ZstdError, EOFError) as error:
            raise ValueError(f"{source}: not a zstd file ({error})") from None


def recover(bag: Path) -> int | None:
    """Rewrite a bag whose recorder died: every complete message of its MCAP file, in recording
    order, with index, summary and metadata.yaml (custom_data kept, message_counts recounted).
    The unindexed file is kept beside it as `<name>.mcap.unindexed`. Returns the number of
    messages recovered, or None when the bag was complete already. Only regular files inside
    the bag are read or renamed, and nothing is changed unless at least one message is
    recovered (ValueError otherwise). A bag the system fails to read (permission denied, an
    I/O error) is an OSError, never taken for an incomplete one."""
    if (bag / "metadata.yaml").is_symlink() or (bag / "metadata.yaml").exists():
        _file_in_bag(bag, "metadata.yaml", "bag file")  # a FIFO here would block the read
    information = bag_information(bag)
    files = information.get("relative_file_paths") or []
    if not isinstance(files, list):
        raise ValueError(f"{bag / 'metadata.yaml'}: relative_file_paths is not a list")
    sources = [_file_in_bag(bag, entry) for entry in files]  # before any file is opened
    custom = information.get("custom_data") or {}
    if not (isinstance(custom, dict)
            and all(isinstance(k, str) and isinstance(v, str) for k, v in custom.items())):
        raise ValueError(f"{bag / 'metadata.yaml'}: custom_data is not a mapping of text to "
                         f"text")
    check_unpacked_size(bag, information)  # before rosbags unpacks anything
    try:
        with Reader(bag):
            return None
    except STORAGE_FAULTS as error:
        if (failure := _read_error(error)) is not None:
            raise OSError(f"{bag}: cannot be read ({failure}); not recovered, nothing "
                          f"changed") from failure
        # otherwise not a complete bag: recover it
    if information.get("storage_identifier") != "mcap" or len(files) != 1:
        raise ValueError(f"{bag}: only single-file MCAP bags can be recovered")
    if compression_mode(information):
        raise ValueError(f"{bag}: only uncompressed bags can be recovered (compression_mode "
                         f"{information.get('compression_mode')!r})")
    source, target = sources[0], bag / f"{bag.name}.mcap"
    unindexed = source.with_name(source.name + ".unindexed")
    for taken in (unindexed, target):
        if taken != source and (taken.is_symlink() or taken.exists()):
            raise ValueError(f"{bag}: {taken.name} exists already; recovery would replace it")
    with _termination_raises():  # so that `finally` removes the scratch on SIGTERM and SIGHUP
        return _rewrite(bag, source, target, unindexed, custom)


def _rewrite(bag: Path, source: Path, target: Path, unindexed: Path,
             custom: dict[str, str]) -> int:
    """`recover`'s work once the bag is checked: the new bag is written in a scratch folder
    inside the bag, renamed into place, and the scratch removed whatever happens."""
    scratch = Path(tempfile.mkdtemp(prefix=".recovering-", dir=bag)) / bag.name
    typestore = get_typestore(Stores.ROS2_JAZZY)
    counts: Counter[str] = Counter()
    try:
        writer = Writer(scratch, version=BAG_VERSION, storage_plugin=StoragePlugin.MCAP)
        writer.open()
        connections = {}
        with source.open("rb") as stream:
            for schema, channel, message in _complete_messages(stream):
                connection = connections.get(channel.id)
                if connection is None:
                    if schema is None:
                        raise ValueError(f"{source}: channel {channel.topic} has no schema")
                    qos = parse_qos(channel.metadata.get("offered_qos_profiles", ""))
                    connection = connections[channel.id] = writer.add_connection(
                        channel.topic, schema.name, typestore=typestore,
                        serialization_format=channel.message_encoding,
                        offered_qos_profiles=qos)
                writer.write(connection, message.log_time, message.data)
                counts[channel.topic] += 1
        if not counts:
            raise ValueError(f"{source}: nothing to recover ({_why_empty(source)}); the bag is "
                             f"left as it is")
        custom_data = dict(custom)
        custom_data["message_counts"] = json.dumps(dict(counts))
        custom_data[RECORDER_STATE] = (f"recovered by recover_bag: {counts.total()} complete "
                                       f"messages; the recorder had died before closing the bag")
        for key, value in custom_data.items():
            writer.set_custom_data(key, value)
        writer.close()
        with _signals_held():  # the three renames are not cut in between
            source.replace(unindexed)
            (scratch / f"{bag.name}.mcap").replace(target)
            (scratch / "metadata.yaml").replace(bag / "metadata.yaml")
    finally:
        shutil.rmtree(scratch.parent, ignore_errors=True)
    return counts.total()


TERMINATING = (signal.SIGTERM, signal.SIGHUP)  # SIGINT raises KeyboardInterrupt already


@contextmanager
def _termination_raises() -> Iterator[None]:
    """SIGTERM and SIGHUP raise SystemExit(128 + signal) inside the block (in the main thread,
    the only one that can set handlers, and where they would end the process: one ignored, as
    under nohup, stays ignored), so that `finally` clauses run and the process still ends with
    the status a kill by that signal reports to a shell."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def terminate(signum: int, _frame: object) -> None:
        raise SystemExit(128 + signum)

    previous = {number: signal.signal(number, terminate) for number in TERMINATING
                if signal.getsignal(number) == signal.SIG_DFL}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


@contextmanager
def _signals_held() -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP held back inside the block and delivered after it."""
    held = {signal.SIGINT, *TERMINATING}
    before = signal.pthread_sigmask(signal.SIG_BLOCK, held)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)


def _file_in_bag(bag: Path, entry: object,
                 what: str = "relative_file_paths entry") -> Path:
    """The file a metadata entry names, where rosbags' Reader looks for it (`bag / name`), if it
    is a regular file inside the bag: recovery renames it, so an entry must not reach a file
    elsewhere (an absolute path, `..`, a symlink out), and a FIFO would block the open."""
    if not isinstance(entry, str) or not entry:
        raise ValueError(f"{bag}: {what} {entry!r} is not a file name")
    relative = PurePath(entry)
    if relative.is_absolute() or ".." in relative.parts:
        raise ValueError(f"{bag}: {what} {entry!r} is outside the bag; refused")
    path = bag / relative.name
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError) as error:  # a symlink loop
        raise ValueError(f"{bag}: {what} {entry!r}: {error}") from None
    if not resolved.is_relative_to(bag.resolve()):
        raise ValueError(f"{bag}: {what} {entry!r} links outside the bag (to {resolved}); "
                         "refused")
    try:
        mode = os.stat(path).st_mode  # stat, not open: opening a FIFO blocks
    except FileNotFoundError:
        raise ValueError(f"{bag}: {what} {entry!r}: no such file in the bag") from None
    if not stat.S_ISREG(mode):
        raise ValueError(f"{bag}: {what} {entry!r} is not a regular file; refused")
    return path


def _read_error(error: BaseException) -> OSError | None:
    """The system's failure to read a bag behind what opening it with rosbags raised, if that
    is what it was: an OSError other than EINVAL (which rosbags' seek to the footer raises on
    a file too short to hold one: a fault of the bag), or the OSError a ReaderError was raised
    from (a storage file rosbags could not open: permission denied)."""
    for fault in (error, error.__cause__):
        if isinstance(fault, OSError) and fault.errno != errno.EINVAL:
            return fault
    return None


def _why_empty(source: Path) -> str:
    """Why a file gave no message, in words for the one-line error."""
    with source.open("rb") as stream:
        head = stream.read(len(MCAP_MAGIC))
    if not head:
        return "the file is empty"
    if head != MCAP_MAGIC:
        return "not an MCAP file"
    return "not a complete MCAP file: no complete message in it"


def _complete_messages(stream):
    """(schema, channel, message) of every whole record, up to where the file was cut off (a
    cut inside a record's fixed-size fields surfaces as struct.error)."""
    try:
        yield from NonSeekingReader(stream).iter_messages(log_time_order=False)
    except (McapError, EOFError, struct.error):
        return


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(
        "recover_bag",
        "Index a rosbag2 MCAP bag whose recorder was killed (SIGKILL, a crash): "
                    "every message written to disk before the kill (the recorder writes twice a "
                    "second) is kept, the bag gets its index and metadata.yaml, and the "
                    "unindexed file stays beside it as <name>.mcap.unindexed. A complete bag is "
                    "left as it is. A bag compressed per file is refused if it would unpack to "
                    f"more than {MAX_UNPACK_RATIO} times its size (at least "
                    f"{MIN_UNPACK_LIMIT >> 20} MiB always pass); one compressed per message "
                    "(compression_mode: message) is refused, as rosbags unpacks its messages "
                    "without a limit. A bag that cannot be read (permission denied, an I/O "
                    "error) is reported, never recovered.")
    parser.add_argument("bag", type=Path, help="the bag directory (holds metadata.yaml)")
    return run_command(report_recovery, parser.parse_args(argv), "recover_bag")


def report_recovery(args: argparse.Namespace) -> int:
    recovered = recover(args.bag)
    if recovered is None:
        print(f"{args.bag}: complete already, nothing to do")
    else:
        print(f"{args.bag}: {recovered} messages recovered and indexed")
    return 0


if __name__ == "__main__":
    sys.exit(main())
