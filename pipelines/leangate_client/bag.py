"""ROS bags in, keyframes out: ``leangate-client BAG --topic IMAGE_TOPIC --out OUT``.

BAG is a ROS 1 ``.bag`` file or a ROS 2 bag folder (sqlite3 or MCAP storage), read with the
pure-Python ``rosbags`` library (no ROS installation). The images of IMAGE_TOPIC are pushed one
by one through the real element (``FrameGate``), and OUT, a bag of the same kind and storage,
gets:

- IMAGE_TOPIC with only the kept messages, their serialised bytes and bag timestamps as they
  were (nothing is deserialised and serialised again);
- every other topic copied whole, in order, with its connection (type, definition, hash, QoS or
  callerid/latching);
- ``IMAGE_TOPIC/leangate``: one ``diagnostic_msgs/msg/DiagnosticArray`` per keep (its header
  stamp the image's), whose one status carries the element's meta as key/values (``frame``,
  ``stamp_ns``, ``utility``, ``reason``, ``keyframe_index``, ``reference_stamp_ns``,
  ``frames_since_keyframe``, and ``partner:TOPIC`` for each rig camera);
- with more ``--topic``s (a camera rig), of each further camera the message nearest in stamp to
  each keep, within half that camera's median frame interval; a keep without one in range is
  kept all the same and counted (``unmatched`` in the summary, ``partner:TOPIC`` = ``none``).

Stamps are the header stamps (the bag time where a header stamp is zero). The bag is read
twice, streaming: once for the gated and rig topics (the gate's decisions and the rig's
stamps), once to write OUT; memory holds a few frames and a few integers per message of those
topics, whatever the bag's size. OUT is written beside its place (a hidden staging file or
folder) and takes it only when the run succeeded, so a failed or interrupted run leaves no OUT
(or the earlier one, with ``--overwrite``), and the input is only read.

In Python: ``gate_bag("run.bag", ["/cam0/image_raw"], "kf.bag")`` returns a ``BagSummary``.
"""

from __future__ import annotations

import bisect
import logging
import os
import shutil
import statistics
from array import array
from dataclasses import dataclass, field
from typing import Any, Callable, Dict, Iterator, List, Optional, Sequence, Tuple

from . import _outdir
from ._bag_image import IMAGE_TYPES, SUPPORTED, ImageError, header_stamp, to_push
from .errors import SetupError

log = logging.getLogger(__name__)

ROSBAGS_VERSION = "0.11.9"
#: The decisions topic is ``<gated topic>`` + this.
DECISIONS_SUFFIX = "/leangate"
DECISIONS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
#: Files of a ROS 2 bag folder's storage.
ROS2_STORAGE_EXT = (".db3", ".mcap")
ROS1_MAGIC = b"#ROSBAG V2.0\n"


def _rosbags():
    """The rosbags modules, or SetupError saying how to get them."""
    try:
        import rosbags.rosbag1 as r1
        import rosbags.rosbag2 as r2
        import rosbags.typesys as ts
    except ImportError as e:
        raise SetupError(
            f"reading ROS bags needs the Python package rosbags ({e}): pip install "
            f"rosbags=={ROSBAGS_VERSION} into the Python that runs leangate-client (a venv made "
            "with --system-site-packages keeps PyGObject); docs/python.md, \"ROS bags\""
        ) from None
    return r1, r2, ts


def is_bag(path) -> bool:
    """Whether ``path`` names a ROS bag (by its look, not read): a ``.bag`` file or a file
    starting with ROS 1's magic line, a ROS 2 storage file (``.db3``/``.mcap``), or a folder
    with ``metadata.yaml`` or a ``.db3``/``.mcap`` file."""
    p = os.fspath(path)
    if os.path.isdir(p):
        try:
            names = os.listdir(p)
        except OSError:
            return False
        return "metadata.yaml" in names or any(n.endswith(ROS2_STORAGE_EXT) for n in names)
    if os.path.isfile(p):
        if p.endswith((".bag", ".bag.active") + ROS2_STORAGE_EXT):
            return True
        try:
            with open(p, "rb") as f:
                return f.read(len(ROS1_MAGIC)) == ROS1_MAGIC
        except OSError:
            return False
    return False


# -- the input ---------------------------------------------------------------------------------
@dataclass
class _Topic:
    name: str
    msgtype: str
    count: int
    connections: list


class BagInput:
    """An opened bag (``open_bag``): its kind, storage and topics."""

    def __init__(self, path: str, reader, ros2: bool, storage: Optional[str], version: int):
        self.path = path
        self.reader = reader
        self.ros2 = ros2
        self.storage = storage
        self.version = version
        self.topics: Dict[str, _Topic] = {}
        for c in reader.connections:
            t = self.topics.get(c.topic)
            if t is None:
                self.topics[c.topic] = _Topic(c.topic, c.msgtype, c.msgcount, [c])
            else:
                t.connections.append(c)
                t.count += c.msgcount
                if t.msgtype != c.msgtype:
                    t.msgtype = f"{t.msgtype}|{c.msgtype}"

    @property
    def kind(self) -> str:
        return f"ros2-{self.storage}" if self.ros2 else "ros1"

    def image_topics(self) -> str:
        """The image topics, with their types and counts, for an error message."""
        imgs = [t for t in self.topics.values() if t.msgtype in IMAGE_TYPES]
        if not imgs:
            return "it has no image topic (sensor_msgs/msg/Image or CompressedImage)"
        return "its image topics: " + ", ".join(
            f"{t.name} ({t.msgtype}, {t.count} messages)" for t in sorted(imgs, key=lambda t: t.name)
        )

    def messages(self, connections: Sequence = ()) -> Iterator[Tuple[Any, int, bytes]]:
        """The reader's messages (all, or of ``connections``), a read error as SetupError."""
        it = self.reader.messages(connections=list(connections))
        n = 0
        while True:
            try:
                item = next(it)
            except StopIteration:
                return
            except Exception as e:  # rosbags, sqlite (apsw), lz4/zstd, struct: all "unreadable"
                raise SetupError(
                    f"{self.path}: cannot be read after {n} messages, truncated or corrupt "
                    f"({type(e).__name__}: {e})"
                ) from None
            n += 1
            yield item

    def close(self) -> None:
        try:
            self.reader.close()
        except Exception:  # noqa: BLE001 - closing a reader that failed to read
            pass


def open_bag(path) -> BagInput:
    """Open BAG for reading, or SetupError naming what is wrong with it: not a bag, a bag still
    being recorded (no index / no metadata.yaml), truncated or corrupt."""
    r1, r2, _ = _rosbags()
    p = os.fspath(path)
    if not os.path.exists(p):
        raise SetupError(f"{p}: no such bag (a ROS 1 .bag file or a ROS 2 bag folder)")
    if os.path.isfile(p) and p.endswith(ROS2_STORAGE_EXT):
        raise SetupError(
            f"{p} is a ROS 2 bag's storage file: give its folder ({os.path.dirname(p) or '.'}, "
            "which holds metadata.yaml)"
        )
    if os.path.isdir(p):
        names = os.listdir(p)
        if "metadata.yaml" not in names:
            data = [n for n in names if n.endswith(ROS2_STORAGE_EXT)]
            if data:
                raise SetupError(
                    f"{p} has {', '.join(sorted(data)[:3])} but no metadata.yaml: a ROS 2 bag "
                    "still being recorded (ros2 bag record writes metadata.yaml when it stops) "
                    "or one whose recording was cut off (`ros2 bag reindex` writes it)"
                )
            raise SetupError(f"{p} is not a ROS 2 bag folder (no metadata.yaml)")
        reader = r2.Reader(p)
        try:
            reader.open()
        except Exception as e:  # noqa: BLE001 - rosbags, yaml, sqlite, mcap errors alike
            raise SetupError(f"{p}: not a readable ROS 2 bag, truncated or corrupt ({e})") from None
        info = _metadata(p)
        bag = BagInput(p, reader, True, str(info.get("storage_identifier") or "sqlite3"),
                       int(info.get("version") or 9))
        bag.compression = (reader.compression_mode, reader.compression_format)
        return bag
    with open(p, "rb") as f:
        magic = f.read(len(ROS1_MAGIC))
    if magic != ROS1_MAGIC:
        raise SetupError(
            f"{p} is not a ROS bag (a ROS 1 bag starts with {ROS1_MAGIC.strip().decode()!r}; a "
            "ROS 2 bag is a folder)"
        )
    reader = r1.Reader(p)
    try:
        reader.open()
    except Exception as e:  # noqa: BLE001
        if "not indexed" in str(e):
            raise SetupError(
                f"{p} has no index: a ROS 1 bag still being recorded, or one whose recording "
                "was cut off (`rosbag reindex` it first)"
            ) from None
        raise SetupError(f"{p}: not a readable ROS 1 bag, truncated or corrupt ({e})") from None
    bag = BagInput(p, reader, False, None, 2)
    bag.compression = None
    return bag


def _metadata(folder: str) -> Dict[str, Any]:
    """``rosbag2_bagfile_information`` of a ROS 2 bag's metadata.yaml (rosbags read it already)."""
    from ruamel.yaml import YAML

    with open(os.path.join(folder, "metadata.yaml")) as f:
        doc = YAML(typ="safe").load(f)
    return doc.get("rosbag2_bagfile_information", {}) if isinstance(doc, dict) else {}


# -- the checks --------------------------------------------------------------------------------
def _real(p: str) -> str:
    return os.path.realpath(p)


def _inside(p: str, d: str) -> bool:
    p, d = _real(p), _real(d)
    return p == d or p.startswith(d.rstrip(os.sep) + os.sep)


def check_topics(bag: BagInput, topics: Sequence[str]) -> Tuple[str, List[str]]:
    """The gated topic and the rig's partner cameras, each an image topic of BAG, or
    SetupError (an unknown topic lists the bag's image topics with types and counts)."""
    if not topics:
        raise SetupError(f"--topic IMAGE_TOPIC is required with a bag; {bag.image_topics()}")
    seen = set()
    for t in topics:
        if t in seen:
            raise SetupError(f"--topic {t} is given twice")
        seen.add(t)
        info = bag.topics.get(t)
        if info is None:
            raise SetupError(f"--topic {t}: {bag.path} has no such topic; {bag.image_topics()}")
        if info.msgtype not in IMAGE_TYPES:
            raise SetupError(
                f"--topic {t} is {info.msgtype}, not an image (sensor_msgs/msg/Image or "
                f"sensor_msgs/msg/CompressedImage); {bag.image_topics()}"
            )
        if info.count == 0:
            raise SetupError(f"--topic {t} has no messages in {bag.path}")
    gated = topics[0]
    decisions = gated + DECISIONS_SUFFIX
    if decisions in bag.topics:
        raise SetupError(
            f"{bag.path} already has the decisions topic {decisions} (an output of leangate-client?)"
        )
    return gated, list(topics[1:])


def check_output(bag: BagInput, out: str, overwrite: bool) -> str:
    """OUT's absolute path, or SetupError: it is BAG, lies in BAG or holds it, exists (without
    ``overwrite``; with it, it must be a bag of the same kind, which is replaced only when the
    run succeeds), or its folder is missing or read-only. Nothing is written."""
    if not out:
        raise SetupError("--out: the path is empty")
    o = os.path.abspath(out)
    if _inside(o, bag.path):
        raise SetupError(f"--out {out} is {'inside ' if _real(o) != _real(bag.path) else ''}the "
                         f"input bag {bag.path}; choose a path outside it")
    if _inside(bag.path, o):
        raise SetupError(f"--out {out} holds the input bag {bag.path}; choose another path")
    kind = "a ROS 2 bag folder" if bag.ros2 else "a ROS 1 bag file"
    if not bag.ros2 and not o.endswith(".bag"):
        raise SetupError(f"--out {out}: the output is {kind} (the input's kind); name it *.bag")
    if bag.ros2 and o.endswith((".bag",) + ROS2_STORAGE_EXT):
        raise SetupError(f"--out {out}: the output is {kind} (the input's kind), not a file")
    if os.path.lexists(o):
        if not overwrite:
            raise SetupError(
                f"--out {out} exists; pass --overwrite to replace it (only when the run succeeds)"
            )
        if os.path.islink(o):
            raise SetupError(f"--out {out} is a symbolic link; give the bag's own path")
        if bag.ros2:
            if not (os.path.isdir(o) and os.path.isfile(os.path.join(o, "metadata.yaml"))):
                raise SetupError(
                    f"--overwrite replaces a ROS 2 bag folder; {out} is not one (no "
                    "metadata.yaml), so it is not replaced"
                )
        else:
            ok = False
            if os.path.isfile(o):
                with open(o, "rb") as f:
                    ok = f.read(len(ROS1_MAGIC)) == ROS1_MAGIC
            if not ok:
                raise SetupError(
                    f"--overwrite replaces a ROS 1 bag file; {out} is not one, so it is not "
                    "replaced"
                )
    parent = os.path.dirname(o)
    if not os.path.isdir(parent):
        raise SetupError(f"--out {out}: the directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise SetupError(f"--out {out}: cannot write to the directory {parent}")
    return o


# -- the output --------------------------------------------------------------------------------
class _Output:
    """OUT being written: a hidden staging file (ROS 1, ``_outdir.AtomicFile``) or folder
    (ROS 2) beside it, that takes OUT's place in ``commit`` (with Ctrl-C, SIGTERM and SIGHUP
    held back, ``_outdir.interrupts_deferred``) or is removed in ``discard``."""

    def __init__(self, bag: BagInput, out: str):
        r1, r2, _ = _rosbags()
        self.out = out
        self.ros2 = bag.ros2
        self.atomic = None
        if bag.ros2:
            from .keyframes import STAGING_TAG, _unused_name

            head, base = os.path.split(out)
            # the bag is written as STAGING/BASE (its storage file BASE/BASE.db3 or .mcap, as
            # OUT will hold it), STAGING a hidden folder beside OUT
            self.staging = _unused_name(head, f".{base}{STAGING_TAG}")
            os.mkdir(self.staging)
            self.bag_dir = os.path.join(self.staging, base)
            version = bag.version if bag.version in (8, 9) else 9
            plugin = r2.StoragePlugin.MCAP if bag.storage == "mcap" else r2.StoragePlugin.SQLITE3
            self.writer = r2.Writer(self.bag_dir, version=version, storage_plugin=plugin)
            mode, fmt = bag.compression
            if mode and fmt and mode != "none":
                self.writer.set_compression(
                    r2.Writer.CompressionMode[mode.upper()], r2.Writer.CompressionFormat[fmt.upper()]
                )
        else:
            self.atomic = _outdir.AtomicFile(out, "wb", open_file=False)
            self.staging = self.atomic.temp
            os.unlink(self.staging)  # the writer makes it itself (and refuses an existing one)
            self.writer = r1.Writer(self.staging)
        self.opened = False
        self.writer.open()
        self.opened = True

    def commit(self) -> None:
        self.writer.close()
        self.opened = False
        if self.atomic is not None:
            self.atomic.commit()
            return
        with _outdir.interrupts_deferred():
            if not os.path.lexists(self.out):
                os.rename(self.bag_dir, self.out)
            elif not _outdir.exchange(self.bag_dir, self.out):
                # no exchange here: the earlier OUT aside (into the staging folder), then the
                # new one in its place (OUT missing for an instant)
                os.rename(self.out, os.path.join(self.staging, ".replaced"))
                os.rename(self.bag_dir, self.out)
            shutil.rmtree(self.staging, ignore_errors=True)  # the replaced bag, if any

    def discard(self) -> None:
        with _outdir.interrupts_deferred():
            if self.opened:
                try:
                    self.writer.abort()
                except Exception:  # noqa: BLE001
                    pass
                self.opened = False
            if self.atomic is not None:
                self.atomic.discard()
                try:
                    os.unlink(self.staging)
                except OSError:
                    pass
            else:
                shutil.rmtree(self.staging, ignore_errors=True)


def _add_connection(writer, ros2: bool, c, typestore):
    """An output connection like the input's ``c`` (a definition missing in an old ROS 2 bag
    is taken from rosbags' standard types)."""
    if not ros2:
        return writer.add_connection(
            c.topic, c.msgtype, msgdef=c.msgdef.data, md5sum=c.digest,
            callerid=c.ext.callerid, latching=c.ext.latching,
        )
    msgdef, digest = c.msgdef.data, c.digest
    if not msgdef or not digest:
        if c.msgtype not in typestore.types:
            raise SetupError(
                f"topic {c.topic} ({c.msgtype}) has no type definition in the bag and is not a "
                "standard ROS 2 type: it cannot be written to OUT"
            )
        msgdef, _ = typestore.generate_msgdef(c.msgtype, ros_version=2)
        digest = typestore.hash_rihs01(c.msgtype)
    return writer.add_connection(
        c.topic, c.msgtype, msgdef=msgdef, rihs01=digest,
        serialization_format=c.ext.serialization_format,
        offered_qos_profiles=c.ext.offered_qos_profiles,
    )


# -- the run -----------------------------------------------------------------------------------
@dataclass
class BagSummary:
    """What ``gate_bag`` did."""

    bag: str
    out: str
    kind: str
    topic: str
    frames_in: int = 0
    kept: int = 0
    decisions_topic: str = ""
    partners: Dict[str, Tuple[int, int]] = field(default_factory=dict)  # topic: (kept, of)
    unmatched: Dict[str, int] = field(default_factory=dict)  # topic: keeps without a partner
    copied: Dict[str, int] = field(default_factory=dict)  # other topics: messages copied
    kept_frames: List[int] = field(default_factory=list)  # indexes in the gated topic
    stats: Any = None

    def line(self) -> str:
        rig = ",".join(f"{t}:{k}/{n}" for t, k, n in
                       ((t, *self.partners[t]) for t in self.partners)) or "-"
        unmatched = ",".join(f"{t}:{n}" for t, n in self.unmatched.items()) or "-"
        copied = ",".join(f"{t}:{n}" for t, n in self.copied.items()) or "-"
        return (
            f"summary: bag={self.bag} kind={self.kind} topic={self.topic} "
            f"frames-in={self.frames_in} kept={self.kept} rig={rig} rig-unmatched={unmatched} "
            f"decisions={self.decisions_topic}:{self.kept} copied={copied} out={self.out}"
        )


def _median_interval(stamps: Sequence[int]) -> Optional[int]:
    diffs = [b - a for a, b in zip(stamps, stamps[1:]) if b > a]
    return int(statistics.median(diffs)) if diffs else None


def _match_partner(keep_stamps: Sequence[int], stamps: array):
    """Of ``stamps`` (a partner camera's, in message order), for each keep stamp the index of
    the nearest within half the camera's median interval, or None (``(indexes, interval)``)."""
    order = sorted(range(len(stamps)), key=stamps.__getitem__)
    s = [stamps[i] for i in order]
    interval = _median_interval(s)
    half = interval // 2 if interval else 0
    found: List[Optional[int]] = []
    for k in keep_stamps:
        j = bisect.bisect_left(s, k)
        best = min((c for c in (j - 1, j) if 0 <= c < len(s)), key=lambda c: abs(s[c] - k),
                   default=None)
        found.append(order[best] if best is not None and abs(s[best] - k) <= half else None)
    return found, interval


def gate_bag(
    bag_path,
    topics: Sequence[str],
    out,
    *,
    overwrite: bool = False,
    progress: Optional[Callable[[str, bool], None]] = None,
    on_keep: Optional[Callable[[Dict[str, Any]], None]] = None,
    **gate_kwargs: Any,
) -> BagSummary:
    """Gate ``topics[0]`` of the bag ``bag_path`` through `leangate` and write ``out`` (see the
    module). ``topics[1:]``: the rig's other cameras. ``gate_kwargs``: ``FrameGate``'s
    (model, threshold, properties, plugin_path, ...). ``progress(text, final)`` is called as
    frames go; ``on_keep(meta)`` for each keep. SetupError for bad input (nothing written),
    PipelineError when the pipeline fails; KeyboardInterrupt leaves no OUT either."""
    _, _, ts = _rosbags()
    bag = open_bag(bag_path)
    try:
        gated, partners = check_topics(bag, list(topics))
        out_path = check_output(bag, os.fspath(out), overwrite)
        summary = BagSummary(bag.path, out_path, bag.kind, gated,
                             decisions_topic=gated + DECISIONS_SUFFIX)
        typestore = ts.get_typestore(ts.Stores.ROS2_HUMBLE if bag.ros2 else ts.Stores.ROS1_NOETIC)
        kept, stamps, partner_stamps = _gate(bag, gated, partners, typestore, summary, progress,
                                             on_keep, gate_kwargs)
        keeps = sorted(kept)
        partner_keep: Dict[str, set] = {}
        partner_of: Dict[int, Dict[str, Optional[int]]] = {i: {} for i in keeps}
        for p in partners:
            found, interval = _match_partner([stamps[i] for i in keeps], partner_stamps[p])
            partner_keep[p] = {j for j in found if j is not None}
            missing = found.count(None)
            for i, j in zip(keeps, found):
                partner_of[i][p] = None if j is None else partner_stamps[p][j]
            summary.partners[p] = (len(partner_keep[p]), len(partner_stamps[p]))
            summary.unmatched[p] = missing
            log.info("%s: median interval %s ms, %d of %d keeps with a partner", p,
                     "-" if interval is None else f"{interval / 1e6:.1f}",
                     len(keeps) - missing, len(keeps))
            if missing:
                log.warning("%s: %d keep(s) of %s have no %s message within half its frame "
                            "interval (kept without it)", p, missing, gated, p)
        _write(bag, gated, partners, kept, stamps, partner_keep, partner_of, typestore, summary,
               progress)
        return summary
    finally:
        bag.close()


def _gate(bag, gated, partners, typestore, summary, progress, on_keep, gate_kwargs):
    """Pass 1: the gated topic's images through the gate; the partners' stamps."""
    from .push import FrameGate

    np = __import__("numpy")
    deser = typestore.deserialize_cdr if bag.ros2 else typestore.deserialize_ros1
    total = bag.topics[gated].count
    conns = bag.topics[gated].connections + [c for p in partners for c in bag.topics[p].connections]
    stamps = array("q")  # the gated messages' stamps (header, else bag time), by index
    pts_of = array("q")  # the pts each was pushed with
    partner_stamps = {p: array("q") for p in partners}
    kept: Dict[int, Dict[str, Any]] = {}
    first: Optional[int] = None
    last_pts = -1
    bumped = 0
    gate_kwargs = dict(gate_kwargs)
    gate_kwargs.setdefault("arrays", False)
    # FrameGate waits for room in steps of up to 20 ms on its appsink, where in drop mode few
    # frames arrive: with its default 4 queued frames that wait, not decoding, bounded the speed
    # (1.7x the video path's time on tum_fr1_desk); 16 frames in flight keep the decoder busy.
    gate_kwargs.setdefault("queue", 16)
    gate_kwargs.setdefault("label", f"{bag.path} {gated}")

    def take(frames):
        for _frame, meta in frames:
            if not meta["keep"]:
                continue
            i = meta["frame"]
            ref = meta.get("reference_pts")
            j = bisect.bisect_left(pts_of, ref) if ref is not None else len(pts_of)
            meta["reference_stamp"] = stamps[j] if j < len(pts_of) and pts_of[j] == ref else None
            kept[i] = meta
            if on_keep:
                on_keep({**meta, "stamp": stamps[i]})

    with FrameGate(**gate_kwargs) as gate:
        for conn, t, raw in bag.messages(conns):
            if conn.topic != gated:
                partner_stamps[conn.topic].append(header_stamp(raw, bag.ros2) or t)
                continue
            i = len(stamps)
            try:
                msg = deser(raw, conn.msgtype)
                image, fmt = to_push(np, msg, conn.msgtype)
            except ImageError as e:
                raise SetupError(f"{gated} message {i} (bag time {t}): {e}") from None
            except Exception as e:  # noqa: BLE001 - a message that does not deserialise
                raise SetupError(
                    f"{gated} message {i} (bag time {t}) cannot be decoded as {conn.msgtype}: "
                    f"{type(e).__name__}: {e}"
                ) from None
            stamp = header_stamp(raw, bag.ros2) or t
            if first is None:
                first = stamp
            pts = stamp - first
            if pts <= last_pts:
                pts = last_pts + 1
                bumped += 1
            last_pts = pts
            stamps.append(stamp)
            pts_of.append(pts)
            try:
                out = gate.push(image, pts, format=fmt)
            except (TypeError, ValueError) as e:
                raise SetupError(f"{gated} message {i} (bag time {t}): {e}") from None
            take(out)
            summary.frames_in = i + 1
            if progress:
                progress(f"{gated}: {i + 1}/{total} frames gated, {len(kept)} kept", False)
        take(gate.finish())
        summary.stats = gate.stats
    if bumped:
        log.info("%s: %d stamps did not increase; pushed 1 ns after the previous one", gated,
                 bumped)
    if not stamps:
        raise SetupError(f"--topic {gated} has no messages in {bag.path}")
    summary.kept = len(kept)
    summary.kept_frames = sorted(kept)
    return kept, stamps, partner_stamps


def _decision(typestore, ros2: bool, topic: str, index: int, stamp: int, frame_id: str,
              meta: Dict[str, Any], partners: Dict[str, Optional[int]]):
    """The DiagnosticArray of one keep."""
    T = typestore.types
    Time = T["builtin_interfaces/msg/Time"]
    Header = T["std_msgs/msg/Header"]
    KeyValue = T["diagnostic_msgs/msg/KeyValue"]
    Status = T["diagnostic_msgs/msg/DiagnosticStatus"]
    Array = T[DECISIONS_TYPE]
    st = Time(sec=stamp // 1_000_000_000, nanosec=stamp % 1_000_000_000)
    header = (Header(stamp=st, frame_id=frame_id) if ros2
              else Header(seq=index, stamp=st, frame_id=frame_id))
    ref = meta.get("reference_stamp")
    values = [
        ("frame", index),
        ("stamp_ns", stamp),
        ("utility", "nan" if meta["utility"] != meta["utility"] else f"{meta['utility']:.6f}"),
        ("reason", meta["reason"]),
        ("keyframe_index", meta["keyframe_index"]),
        ("reference_stamp_ns", "" if ref is None else ref),
        ("frames_since_keyframe", meta.get("frames_since_keyframe", "")),
    ] + [(f"partner:{p}", "none" if s is None else s) for p, s in partners.items()]
    status = Status(
        level=0, name="leangate", message=f"keep ({meta['reason']})", hardware_id=topic,
        values=[KeyValue(key=k, value=str(v)) for k, v in values],
    )
    msg = Array(header=header, status=[status])
    if ros2:
        return typestore.serialize_cdr(msg, DECISIONS_TYPE)
    return typestore.serialize_ros1(msg, DECISIONS_TYPE)


def _write(bag, gated, partners, kept, stamps, partner_keep, partner_of, typestore, summary,
           progress):
    """Pass 2: OUT, every message in bag order (the gated and rig topics filtered)."""
    deser = typestore.deserialize_cdr if bag.ros2 else typestore.deserialize_ros1
    out = _Output(bag, summary.out)
    try:
        conn_map: Dict[int, Any] = {}
        made: Dict[tuple, Any] = {}
        for c in bag.reader.connections:
            key = (c.topic, c.msgtype, repr(c.ext))
            if key not in made:
                made[key] = _add_connection(out.writer, bag.ros2, c, typestore)
            conn_map[id(c)] = made[key]
        dts = typestore
        if bag.ros2:
            msgdef, _ = dts.generate_msgdef(DECISIONS_TYPE, ros_version=2)
            dconn = out.writer.add_connection(
                summary.decisions_topic, DECISIONS_TYPE, msgdef=msgdef,
                rihs01=dts.hash_rihs01(DECISIONS_TYPE),
            )
        else:
            msgdef, md5 = dts.generate_msgdef(DECISIONS_TYPE, ros_version=1)
            dconn = out.writer.add_connection(
                summary.decisions_topic, DECISIONS_TYPE, msgdef=msgdef, md5sum=md5,
                callerid="/leangate",
            )
        index = {gated: 0, **{p: 0 for p in partners}}
        copied: Dict[str, int] = {}
        total = sum(t.count for t in bag.topics.values())
        done = 0
        for conn, t, raw in bag.messages():
            done += 1
            topic = conn.topic
            w = conn_map[id(conn)]
            if topic == gated:
                i = index[topic]
                index[topic] += 1
                if i in kept:
                    out.writer.write(w, t, raw)
                    frame_id = str(deser(raw, conn.msgtype).header.frame_id)
                    out.writer.write(dconn, t, _decision(
                        typestore, bag.ros2, gated, i, stamps[i], frame_id, kept[i],
                        partner_of.get(i, {})))
            elif topic in index:
                j = index[topic]
                index[topic] += 1
                if j in partner_keep[topic]:
                    out.writer.write(w, t, raw)
            else:
                out.writer.write(w, t, raw)
                copied[topic] = copied.get(topic, 0) + 1
            if progress:
                progress(f"writing {summary.out}: {done}/{total} messages", False)
        summary.copied = {t: copied.get(t, 0) for t in sorted(bag.topics)
                          if t != gated and t not in partners}
        out.commit()
    except BaseException:
        out.discard()
        raise


__all__ = ["gate_bag", "open_bag", "is_bag", "check_topics", "check_output", "BagSummary",
           "BagInput", "DECISIONS_SUFFIX", "DECISIONS_TYPE"]
