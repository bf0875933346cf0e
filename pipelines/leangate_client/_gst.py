"""The GStreamer bindings (imported lazily-failing) and finding the `leangate` plugin."""

from __future__ import annotations

import logging
import math
import os
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


def _check_range(el, prop: str, value: Any) -> None:
    """SetupError for a number outside the range of ``prop``'s GParamSpec (GLib would only
    print a warning and leave the property as it was), or NaN for a floating-point one."""
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
            f"bad value {value!r} for {_factory_name(el)} property {prop}: "
            f"it must be in [{lo}, {hi}]"
        )


def _set(el, prop: str, value: Any) -> None:
    """``el.set_property`` with a SetupError (naming the accepted values, or the accepted range
    of a number) for a bad value."""
    _check_range(el, prop, value)
    try:
        el.set_property(prop, value)
    except (TypeError, ValueError, OverflowError) as e:
        nicks = _enum_nicks(el, prop)
        known = f"; one of: {', '.join(nicks)}" if nicks else ""
        raise SetupError(
            f"bad value {value!r} for {_factory_name(el)} property {prop}{known} ({e})"
        ) from None
