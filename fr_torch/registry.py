"""One plug-in registry, one method-spec grammar and one "not supplied" marker for the whole project.

**Registries.**  Calibrators (:data:`fr_torch.plugins.interface.CALIBRATORS`), line detectors
(:data:`fr_torch.detectors.registry.DETECTORS`) and the harness's datasets are :class:`Registry` objects.  A
name is found, in this order, among

1. factories registered in code (``REGISTRY.register(name, factory)`` or as a decorator);
2. Python entry points of the registry's group (``fr_torch.calibrators``, ``fr_torch.detectors``,
   ...), declared by any installed distribution -- this project's own methods included (see
   ``[project.entry-points.*]`` in ``pyproject.toml``) -- and loaded only when first used, so a
   broken or slow optional plug-in costs nothing until it is asked for;
3. an import path ``"package.module:attribute"`` (no installation needed).  Such a path is called
   only when what it names declares itself a plug-in of the registry's kind (:meth:`Registry.factory`):
   a class implementing the kind's protocol (a calibrator class has ``estimate(image, meta)``), a
   factory registered in this registry or marked with :func:`plugin`, or an entry point's target;
   anything else (``subprocess:getoutput``) is a one-line error and nothing is called.

A third-party package therefore adds a method without editing this project::

    # its pyproject.toml
    [project.entry-points."fr_torch.calibrators"]
    horizon-lines = "fr_plugin_example:HorizonFromLines"

(see ``examples/fr_plugin_example``).  A source checkout runs through an editable install
(``pip install -e .``), which declares this project's own entry points the same way.

**Method specs.**  ``name[key=value,key=value]`` selects a registered factory and passes the options
as keyword arguments (strings): ``fr[measure=a]``, ``fast-fr[detector=mcmlsd]``.
:func:`parse_method_spec` and :func:`format_method_spec` are the only parser / printer of it.
An option the factory's signature does not take is a one-line error; options a caller merely
offers (``fr eval``'s ``device``) go only to factories that take them (:meth:`Registry.create`;
``docs/plugins-options.md``).

**Not supplied.**  A method whose weights or predictions the user did not supply fails every image
with a reason starting with :data:`NA_PREFIX`; :data:`NOT_SUPPLIED` is the marker the tables show and
:func:`not_supplied` builds the per-image reason (``"n/a (not supplied: <what is missing>)"``).
"""
from __future__ import annotations

import importlib
import importlib.metadata
import importlib.util
import inspect
import re
from typing import Any, Callable, Generic, Iterable, TypeVar

T = TypeVar("T")

NA_PREFIX = "n/a ("
NOT_SUPPLIED = "n/a (not supplied)"


def not_supplied(detail: str = "") -> str:
    """Failure reason of a method whose weights / predictions are missing.

    ``not_supplied()`` -> ``"n/a (not supplied)"``;
    ``not_supplied("set FR_CTRLC_ONNX")`` -> ``"n/a (not supplied: set FR_CTRLC_ONNX)"``.
    Every such reason starts with :data:`NA_PREFIX` (what the harness and tables test for)."""
    return f"{NOT_SUPPLIED[:-1]}: {detail})" if detail else NOT_SUPPLIED


def is_not_supplied(reason: str | None) -> bool:
    """True for an "n/a (...)" reason (see :func:`not_supplied`)."""
    return str(reason or "").startswith(NA_PREFIX)


# --------------------------------------------------------------------------- method specs

_SPEC = re.compile(r"^(?P<name>[^\[\]]+)\[(?P<options>[^\[\]]*)\]$")


def parse_method_spec(spec: str, strict: bool = True) -> tuple[str, dict[str, str]]:
    """``"fr[measure=a,detector=mcmlsd]"`` -> ``("fr", {"measure": "a", "detector": "mcmlsd"})``.

    A spec without brackets is a bare name (``"fr"`` -> ``("fr", {})``), import paths included
    (``"pkg.mod:Class[x=1]"`` -> ``("pkg.mod:Class", {"x": "1"})``).  Values are strings.  With
    ``strict`` an option without ``=`` or unbalanced brackets raise ``ValueError``; otherwise (for
    reading labels back, e.g. ``"fr[measure=a]@labelled"``) such a spec is returned whole as the
    name and an option without ``=`` gets the value ``""``."""
    spec = spec.strip()
    if "[" not in spec and "]" not in spec:
        return spec, {}
    match = _SPEC.match(spec)
    if not match:
        if strict:
            raise ValueError(f"bad method spec {spec!r}: use name[key=value,...]")
        return spec, {}
    options: dict[str, str] = {}
    for item in filter(None, (part.strip() for part in match["options"].split(","))):
        key, eq, value = item.partition("=")
        if strict and (not eq or not key.strip()):
            raise ValueError(f"bad option {item!r} in method {spec!r}: use key=value")
        options[key.strip()] = value.strip()
    return match["name"].strip(), options


def split_method_list(text: str) -> list[str]:
    """Split a comma-separated list of specs, keeping commas inside ``[...]``:
    ``"fr[measure=a,detector=lsd],lee2009"`` -> ``["fr[measure=a,detector=lsd]", "lee2009"]``."""
    out, depth, current = [], 0, []
    for ch in text:
        if ch == "[":
            depth += 1
        elif ch == "]":
            depth = max(0, depth - 1)
        if ch == "," and depth == 0:
            out.append("".join(current).strip())
            current = []
        else:
            current.append(ch)
    out.append("".join(current).strip())
    return [m for m in out if m]


def format_method_spec(name: str, options: dict[str, Any] | None = None) -> str:
    """Inverse of :func:`parse_method_spec`: ``("fr", {"measure": "a"})`` -> ``"fr[measure=a]"``
    (options in the given order; ``None`` values are left out)."""
    items = [f"{k}={v}" for k, v in (options or {}).items() if v is not None]
    return f"{name}[{','.join(items)}]" if items else name


def with_option(spec: str, key: str, value: Any) -> str:
    """``spec`` with option ``key=value`` added or replaced: ``fr`` -> ``fr[measure=a]``."""
    name, options = parse_method_spec(spec, strict=False)
    options[key] = str(value)
    return format_method_spec(name, options)


# --------------------------------------------------------------------------- entry points

def entry_points(group: str) -> dict[str, str]:
    """``{name: "module:attr"}`` of every entry point of ``group`` of the installed distributions
    (this project's own included: run a checkout through ``pip install -e .``)."""
    return {ep.name: ep.value for ep in importlib.metadata.entry_points(group=group)}


def load_object(path: str) -> Any:
    """The object named by ``"package.module:attribute"`` (``attribute`` may be dotted)."""
    module_name, _, attr = path.partition(":")
    obj = importlib.import_module(module_name.strip())
    for part in filter(None, attr.strip().split(".")):
        obj = getattr(obj, part)
    return obj


# --------------------------------------------------------------------------- declarations

PLUGIN_MARK = "__fr_plugin__"  # attribute holding the kinds a class or factory declared (see plugin)


def plugin(kind: str) -> Callable[[T], T]:
    """Decorator declaring a class or factory a plug-in of ``kind`` (``"method"``, ``"detector"``,
    ``"dataset"``), so that it may be named by import path (``fr eval --methods my_mod:make_mine``)::

        @plugin("method")
        def make_mine(**options) -> MyCalibrator: ...
    """
    def mark(obj: T) -> T:
        setattr(obj, PLUGIN_MARK, (*getattr(obj, PLUGIN_MARK, ()), kind))
        return obj

    return mark


def factory_options(factory: Callable) -> tuple[frozenset[str], bool] | None:
    """The keyword options ``factory`` takes: (names, whether it takes ``**options``), or None when
    its signature cannot be read (a builtin)."""
    try:
        signature = inspect.signature(factory)
    except (TypeError, ValueError):
        return None
    kinds = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
    names = frozenset(p.name for p in signature.parameters.values() if p.kind in kinds)
    return names, any(p.kind == inspect.Parameter.VAR_KEYWORD for p in signature.parameters.values())


# --------------------------------------------------------------------------- registry

class Registry(Generic[T]):
    """Named factories of one kind of plug-in (see the module docstring for the lookup order).

    ``kind``: what is registered, for messages ("method", "detector", "dataset").
    ``group``: the entry-point group read lazily (None: none).
    ``modules``: modules imported on first lookup that register factories themselves (kept for
    code that registers several names at once; a module that is not installed is skipped).
    ``implements``: whether a class implements this kind's protocol (a class named by import path
    that does is a plug-in without further declaration); ``protocol``: that protocol in words, for
    messages.
    """

    def __init__(self, kind: str, group: str | None = None, modules: Iterable[str] = (),
                 error: type[Exception] = ValueError, implements: Callable[[type], bool] | None = None,
                 protocol: str = ""):
        self.kind = kind
        self.group = group
        self.modules = tuple(modules)
        self.error = error
        self.implements = implements
        self.protocol = protocol
        self._factories: dict[str, Callable[..., T]] = {}
        self._modules_loaded = False

    def register(self, name: str, factory: Callable[..., T] | None = None):
        """Register ``factory`` under ``name``; without ``factory``, a decorator doing so."""
        if factory is not None:
            self._factories[name] = factory
            return factory

        def deco(f: Callable[..., T]) -> Callable[..., T]:
            self._factories[name] = f
            return f

        return deco

    def _load_modules(self) -> None:
        if self._modules_loaded:
            return
        self._modules_loaded = True
        for module in self.modules:
            try:
                importlib.import_module(module)
            except ModuleNotFoundError as exc:  # not part of this installation
                if exc.name != module and not module.startswith(f"{exc.name}."):
                    raise

    def _entry_points(self) -> dict[str, str]:
        return entry_points(self.group) if self.group else {}

    def names(self) -> list[str]:
        """All names: registered ones and entry points (the latter are listed without importing)."""
        self._load_modules()
        return sorted(set(self._factories) | set(self._entry_points()))

    def __contains__(self, name: str) -> bool:
        return name in self.names()

    def factory(self, name: str) -> Callable[..., T]:
        """The factory for a registered name, an entry point or an import path ``module:attr``."""
        self._load_modules()
        if name in self._factories:
            return self._factories[name]
        target = self._entry_points().get(name)
        if target is not None:
            try:
                factory = load_object(target)
            except Exception as exc:  # noqa: BLE001 - a broken plug-in is a one-line error
                raise self.error(f"cannot load {self.kind} {name!r} from entry point {target!r}: "
                                 f"{type(exc).__name__}: {exc}") from None
            self._factories[name] = factory
            return factory
        if ":" in name:
            try:
                obj = load_object(name)
            except Exception as exc:  # noqa: BLE001 - a missing or broken module is a one-line error
                raise self.error(f"cannot import {self.kind} {name!r}: {type(exc).__name__}: {exc}") from None
            if not self.declared(name, obj):
                ways = (f"{self.protocol}, " if self.protocol else "") + \
                    f"a factory registered as a {self.kind} or marked @fr_torch.registry.plugin({self.kind!r})"
                raise self.error(f"{name!r} is not a {self.kind} plug-in (an import path must name {ways}); "
                                 "nothing was called")
            return obj
        raise self.error(f"unknown {self.kind} {name!r}; available: {', '.join(self.names())} "
                         "(or give an import path module:attribute)")

    def declared(self, path: str, obj: Any) -> bool:
        """Whether ``obj``, found at import path ``path``, declared itself a plug-in of this kind: a
        class implementing the protocol (:attr:`implements`), a factory marked with :func:`plugin`
        or registered here (importing its module ran the registration), or an entry point's target."""
        try:
            if self.kind in getattr(obj, PLUGIN_MARK, ()):
                return True
        except Exception:  # noqa: BLE001 - an object whose attributes misbehave declares nothing
            return False
        if any(obj is factory for factory in self._factories.values()):
            return True
        if "".join(path.split()) in {"".join(v.split()) for v in self._entry_points().values()}:
            return True
        return isinstance(obj, type) and self.implements is not None and bool(self.implements(obj))

    def create(self, spec: str, offered: dict[str, Any] | None = None, **kwargs) -> T:
        """Build from a method spec ``name[key=value,...]``.

        The spec's options and ``kwargs`` (which override them) are passed to the factory; one its
        signature does not take (by name or ``**options``) is an error naming it.  ``offered``:
        options passed only to a factory that takes them and only when the spec does not set them
        (a harness's ``device``; see ``docs/plugins-options.md``)."""
        name, options = parse_method_spec(spec)
        factory = self.factory(name)
        given = {**options, **kwargs}
        takes = factory_options(factory)
        if takes is not None:
            names, any_option = takes
            unknown = [key for key in given if key not in names and not any_option]
            if unknown:
                raise self.error(f"{self.kind} {name!r} takes no option {', '.join(map(repr, unknown))} "
                                 f"(it takes: {', '.join(sorted(names)) or 'none'})")
            given.update({key: value for key, value in (offered or {}).items()
                          if key not in given and (key in names or any_option)})
            if not any_option:
                return factory(**given)
        try:  # a factory that passes **options on: what it cannot take surfaces as a TypeError
            return factory(**given)
        except TypeError as exc:
            raise self.error(f"{self.kind} {spec!r}: {exc}") from None

    def takes(self, spec: str, option: str) -> bool:
        """Whether the factory of ``spec`` takes keyword ``option`` (by name or ``**options``)."""
        takes = factory_options(self.factory(parse_method_spec(spec)[0]))
        return takes is not None and (option in takes[0] or takes[1])

