"""The GStreamer bindings (imported lazily-failing) and finding the `leangate` plugin."""

from __future__ import annotations

import logging
import math
import numbers
import os
import re
import weakref
from typing import Any, Callable, Iterable, List, Optional, Union

from .errors import SetupError

log = logging.getLogger(__name__)

PLUGIN_FILE = "libgstleangate.so"
ELEMENT = "leangate"

try:
    import numpy as np
    import gi

    gi.require_version("Gst", "1.0")
    gi.require_version("GstVideo", "1.0")
    from gi.repository import GLib, GObject, Gst, GstVideo  # noqa: E402
except (ImportError, ValueError) as _e:  # pragma: no cover - exercised only without bindings
    IMPORT_ERROR: Optional[BaseException] = _e
    np = None
    gi = None
    GLib = GObject = Gst = GstVideo = None
else:
    IMPORT_ERROR = None

PathLike = Union[str, "os.PathLike[str]"]


def require_bindings() -> None:
    """Raise SetupError naming the Debian packages when PyGObject/GStreamer/numpy are missing."""
    if IMPORT_ERROR is not None:
        raise SetupError(
            f"cannot import the GStreamer Python bindings or numpy ({IMPORT_ERROR}); on Debian/"
            "Ubuntu: apt install python3-gi gir1.2-gstreamer-1.0 gir1.2-gst-plugins-base-1.0 "
            "python3-numpy (and run with /usr/bin/python3, or a venv created with "
            "--system-site-packages)"
        )


def _init() -> None:
    require_bindings()
    if not Gst.is_initialized():
        Gst.init(None)


def plugin_file() -> Optional[str]:
    """The file the registered `leangate` element comes from (None when it is not found)."""
    _init()
    factory = Gst.ElementFactory.find(ELEMENT)
    if factory is None:
        return None
    plugin = factory.get_plugin()
    return plugin.get_filename() if plugin is not None else None


def _candidate(path: PathLike) -> str:
    """A plugin path argument (the .so itself or the directory holding it) → the .so path."""
    p = os.fspath(path)
    if os.path.isdir(p):
        p = os.path.join(p, PLUGIN_FILE)
    return p


def _load(lib: str) -> bool:
    """Load a plugin file into the default registry; whether `leangate` is then found."""
    try:
        plugin = Gst.Plugin.load_file(lib)
    except GLib.Error as e:
        raise SetupError(f"cannot load the GStreamer plugin {lib}: {e.message}") from None
    Gst.Registry.get().add_plugin(plugin)
    found = plugin_file()
    log.debug("loaded %s; leangate now from %s", lib, found)
    return found is not None


def ensure_plugin(
    plugin_path: Optional[PathLike] = None, fallbacks: Iterable[PathLike] = ()
) -> str:
    """Initialise GStreamer and make sure the `leangate` element exists; return its plugin file.

    Where the plugin comes from, in order:

    1. ``plugin_path`` when given: ``libgstleangate.so`` itself or the directory holding it.
       It is loaded explicitly, unless the registry already has `leangate` from that very file.
    2. GStreamer's own search: ``GST_PLUGIN_PATH`` (the documented way), then the system
       plugin directories.
    3. ``fallbacks`` (files or directories), tried in order, only when 1 and 2 found nothing
       (the repository's ``pipelines/slam_client.py`` passes its ``target/{release,debug}``).

    Raises SetupError when it is still missing.
    """
    _init()
    if plugin_path is not None:
        lib = _candidate(plugin_path)
        if not os.path.isfile(lib):
            raise SetupError(f"leangate plugin not found: {lib} (plugin_path={os.fspath(plugin_path)!r})")
        current = plugin_file()
        if current is not None and os.path.realpath(current) == os.path.realpath(lib):
            return current
        if current is not None:
            log.info(
                "leangate is already registered from %s; loading %s as asked by plugin_path",
                current,
                lib,
            )
        _load(lib)
        found = plugin_file()
        if found is None:
            raise SetupError(f"{lib} loaded, but it does not provide the `leangate` element")
        return found

    found = plugin_file()
    if found is not None:
        return found
    tried = []
    for fb in fallbacks:
        lib = _candidate(fb)
        if os.path.isfile(lib):
            tried.append(lib)
            if _load(lib):
                log.info("leangate not in GST_PLUGIN_PATH; using %s", lib)
                return plugin_file()
    raise SetupError(
        "GStreamer element `leangate` not found. Installed with `make install PREFIX=...` "
        "(other than ~/.local or /usr/local, which GStreamer finds): set "
        "GST_PLUGIN_PATH=$PREFIX/lib/gstreamer-1.0 (docs/install.md). In a checkout: build it "
        "(`cargo build`) and set GST_PLUGIN_PATH to the directory holding libgstleangate.so "
        "(e.g. $PWD/target/debug). Or pass plugin_path= / --plugin-path"
        + (f" (also tried {', '.join(tried)})" if tried else "")
    )


def _make(factory: str, name: Optional[str] = None):
    el = Gst.ElementFactory.make(factory, name)
    if el is None:
        raise SetupError(
            f"GStreamer element `{factory}` not found (Debian: apt install "
            "gstreamer1.0-plugins-base gstreamer1.0-plugins-good)"
        )
    return el


def _enum_nicks(el, prop: str) -> List[str]:
    pspec = el.find_property(prop)
    try:
        return sorted(v.value_nick for v in pspec.enum_class.__enum_values__.values())
    except AttributeError:
        return []


def weak_method(method: Callable, default: Any = None) -> Callable:
    """A callable for a signal or pad probe that holds only a weak reference to ``method``'s
    object: a GObject closure holding a bound method makes a reference cycle that Python's
    garbage collector cannot see, so the object (and what it keeps running) would never be
    freed. Once the object is gone, the call returns ``default``."""
    ref = weakref.WeakMethod(method)

    def call(*args):
        m = ref()
        return default if m is None else m(*args)

    return call


def _factory_name(el) -> str:
    return el.get_factory().get_name() if el.get_factory() else el.get_name()


#: Text for a boolean property, as GStreamer reads it (gst-launch-1.0, ``gst_value_deserialize``;
#: case does not matter).
_BOOLEAN_WORDS = {"true": True, "yes": True, "t": True, "1": True,
                  "false": False, "no": False, "f": False, "0": False}
#: Text for an integer property, as GStreamer reads it (``strtoll`` with base 0): decimal,
#: ``0x`` hexadecimal, or octal with a leading 0 (``010`` is 8, as in gst-launch-1.0).
_INT_TEXT = re.compile(r"([+-]?)(0[xX][0-9a-fA-F]+|0[0-7]*|[1-9][0-9]*)")
#: Text for a floating-point property: a decimal number (exponent allowed), inf or nan.
_FLOAT_TEXT = re.compile(
    r"[+-]?(?:(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|inf|infinity|nan)", re.IGNORECASE
)


def _int_from_text(text: str) -> Optional[int]:
    m = _INT_TEXT.fullmatch(text.strip())
    if m is None:
        return None
    sign, body = m.groups()
    if body[:2] in ("0x", "0X"):
        v = int(body[2:], 16)
    elif body.startswith("0"):
        v = int(body, 8)
    else:
        v = int(body)
    return -v if sign == "-" else v


def _integer_types() -> tuple:
    return (GObject.TYPE_INT, GObject.TYPE_UINT, GObject.TYPE_LONG, GObject.TYPE_ULONG,
            GObject.TYPE_INT64, GObject.TYPE_UINT64, GObject.TYPE_CHAR, GObject.TYPE_UCHAR)


def _coerce(el, prop: str, value: Any) -> Any:
    """``value`` as the type of ``prop`` takes it, converted only when that is exact, else
    SetupError naming the property, the value and what the property takes. PyGObject alone
    converts silently (``True`` or ``2.7`` for an integer gives 1 or 2, any non-empty string
    for a boolean gives True). Accepted besides values of the property's own type: text as
    gst-launch-1.0 reads it (``"false"``, ``"yes"``, ``"0x10"``, ``"2.5"``), a whole float for
    an integer (``3.0``), an integer for a floating-point number, 0 or 1 for a boolean, and an
    os.PathLike for a string. Properties of other types are left to ``set_property``."""
    pspec = el.find_property(prop)
    if pspec is None:
        return value  # set_property names the unknown property
    kind = GObject.type_fundamental(pspec.value_type)
    takes = None
    if kind == GObject.TYPE_BOOLEAN:
        if isinstance(value, (bool, np.bool_)):
            return bool(value)
        if isinstance(value, str) and value.strip().lower() in _BOOLEAN_WORDS:
            return _BOOLEAN_WORDS[value.strip().lower()]
        if isinstance(value, numbers.Integral) and value in (0, 1):
            return bool(value)
        takes = "a boolean (True or False; as text true/false, yes/no, t/f or 1/0)"
    elif kind in _integer_types():
        v: Any = None
        if isinstance(value, (bool, np.bool_)):
            v = None
        elif isinstance(value, numbers.Integral):
            v = int(value)
        elif isinstance(value, numbers.Real):
            f = float(value)
            v = int(f) if math.isfinite(f) and f.is_integer() else None
        elif isinstance(value, str):
            v = _int_from_text(value)
        if v is not None:
            return v
        takes = f"an integer in [{pspec.minimum}, {pspec.maximum}]"
    elif kind in (GObject.TYPE_FLOAT, GObject.TYPE_DOUBLE):
        if isinstance(value, numbers.Real) and not isinstance(value, (bool, np.bool_)):
            try:
                return float(value)
            except OverflowError:  # an int beyond any double
                pass
        if isinstance(value, str) and _FLOAT_TEXT.fullmatch(value.strip()):
            return float(value.strip())
        takes = f"a number in [{pspec.minimum}, {pspec.maximum}]"
    elif kind == GObject.TYPE_ENUM:
        nicks = _enum_nicks(el, prop)
        values = pspec.enum_class.__enum_values__
        if isinstance(value, str) and value in nicks:
            return value
        if isinstance(value, str):  # a value's name, as the element registered it
            for v in values.values():
                if value == v.value_name:
                    return v.value_nick
        if (isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_))
                and int(value) in values):
            return int(value)
        if isinstance(value, str) and _int_from_text(value) in values:  # "1", as gst-launch
            return _int_from_text(value)
        takes = f"one of: {', '.join(nicks)}"
    elif kind == GObject.TYPE_STRING:
        if value is None or isinstance(value, str):
            return value
        if isinstance(value, os.PathLike):
            return os.fspath(value)
        takes = "a string"
    else:
        return value
    raise SetupError(
        f"bad value {value!r} for {_factory_name(el)} property {prop}: it takes {takes}"
    )


def _check_range(el, prop: str, value: Any, given: Any = None) -> None:
    """SetupError for a number outside the range of ``prop``'s GParamSpec (GLib would only
    print a warning and leave the property as it was), or NaN for a floating-point one.
    ``given``: the value as the caller gave it (text, say), named in the message."""
    pspec = el.find_property(prop)
    if pspec is None or isinstance(value, bool) or not isinstance(value, (int, float)):
        return  # unknown property or not a number: set_property says what is wrong
    lo, hi = getattr(pspec, "minimum", None), getattr(pspec, "maximum", None)
    if lo is None or hi is None:
        return  # not a numeric spec (boolean, enum, string, ...)
    if isinstance(value, float) and math.isnan(value):
        bad = True
    else:
        v = value
        if pspec.value_type == GObject.TYPE_FLOAT:  # compared as GLib will store it
            v = float(np.float32(value))
        bad = not lo <= v <= hi
    if bad:
        raise SetupError(
            f"bad value {value if given is None else given!r} for {_factory_name(el)} "
            f"property {prop}: it must be in [{lo}, {hi}]"
        )


def _set(el, prop: str, value: Any) -> None:
    """``el.set_property`` with a SetupError (naming the accepted values, or the accepted range
    of a number) for a bad value: a value of another type is converted only when that is exact
    (``_coerce``), and a number is checked against the property's range."""
    given, value = value, _coerce(el, prop, value)
    _check_range(el, prop, value, given)
    try:
        el.set_property(prop, value)
    except (TypeError, ValueError, OverflowError) as e:
        nicks = _enum_nicks(el, prop)
        known = f"; one of: {', '.join(nicks)}" if nicks else ""
        raise SetupError(
            f"bad value {value!r} for {_factory_name(el)} property {prop}{known} ({e})"
        ) from None


def _depth_mux(plugin: str, intrinsics: str, depth_scale: float):
    """A `leangatedepthmux` named `m` with the camera's intrinsics and depth scale; a clear
    SetupError when the loaded plugin has no such element."""
    if Gst.ElementFactory.find("leangatedepthmux") is None:
        raise SetupError(
            f"depth needs the element leangatedepthmux, which the plugin {plugin} lacks "
            "(a build older than RGB-D support)"
        )
    mux = _make("leangatedepthmux", "m")
    _set(mux, "intrinsics", intrinsics)
    _set(mux, "depth-scale", depth_scale)
    return mux
