"""Generator methods as plug-ins: a registry of method families.

A **family** is a class derived from :class:`party.methods.base.MethodFamily`, registered under
its name with :func:`register`; it lives in its own folder (``party/methods/<name>/``, or any
importable module: a plug-in). ``generator.methods.<m>`` names a family in its ``family`` key,
and the family's ``Config`` dataclass is the schema of that entry. Nothing outside a family's
folder branches on a family or method name: the stages ask the registry.

    from party import methods
    fam = methods.family("party")                    # the family class
    fam = methods.family_of(cfg.generator, "party")  # the family of generator.methods.party
    trained = methods.load_method("data/generators/party")

Built-in families are imported on first look-up; plug-ins are imported from
``generator.plugins`` (a list of module names or ``.py`` files inside the project, each
registering its families on import): ``party params generator.plugins='[my_lab.methods]'``.
"""
from __future__ import annotations

import importlib
from collections.abc import Iterable
from typing import TYPE_CHECKING

if TYPE_CHECKING:                          # pragma: no cover
    from party.methods.base import MethodFamily

#: the modules of the built-in families (imported on first look-up)
BUILTIN = ("party.methods.party", "party.methods.parco", "party.methods.random_codes",
           "party.methods.humantomato.family", "party.methods.textim.family")

_FAMILIES: dict[str, type] = {}
_loaded: set[str] = set()


def register(cls: type) -> type:
    """Class decorator: add a ``MethodFamily`` subclass to the registry under ``cls.name``."""
    name = getattr(cls, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"{cls.__qualname__}: a method family needs a ``name`` that is an identifier, got {name!r}")
    have = _FAMILIES.get(name)
    if have is not None and have.__qualname__ != cls.__qualname__:
        raise ValueError(f"method family {name!r} is registered twice ({have.__module__}.{have.__qualname__} "
                         f"and {cls.__module__}.{cls.__qualname__})")
    _FAMILIES[name] = cls
    return cls


def _import_file(spec: str) -> None:
    """Import the plug-in file ``spec`` (a ``.py`` path inside the working directory)."""
    import importlib.util
    import sys
    from pathlib import Path
    root = Path.cwd().resolve()
    path = (root / spec).resolve()
    if not path.is_relative_to(root):
        raise ValueError(f"generator.plugins: {spec!r} lies outside the project ({root})")
    if not path.is_file():
        raise ImportError(f"generator.plugins: {spec}: no such file")
    name = "party_plugin_" + "_".join(path.relative_to(root).with_suffix("").parts)
    if not name.isidentifier():
        raise ValueError(f"generator.plugins: {spec!r}: a plug-in file's path must be made of identifiers")
    mspec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(mspec)
    sys.modules[name] = module
    try:
        mspec.loader.exec_module(module)
    except BaseException:
        del sys.modules[name]
        raise


def load_plugins(modules: Iterable[str] = ()) -> None:
    """Import the built-in families and the plug-ins ``modules`` (``generator.plugins``: module
    names, or ``.py`` files inside the project), once each."""
    for mod in (*BUILTIN, *(modules or ())):
        mod = str(mod)
        if mod in _loaded:
            continue
        is_file = mod.endswith(".py")
        if not is_file and not all(p.isidentifier() for p in mod.split(".")):
            raise ValueError(f"generator.plugins: {mod!r} is neither a module name nor a .py file")
        try:
            _import_file(mod) if is_file else importlib.import_module(mod)
        except ImportError as e:
            raise ImportError(f"generator.plugins: cannot import method plug-in {mod!r} ({e})") from e
        _loaded.add(mod)


def families() -> dict[str, type]:
    """The registered families by name (built-ins imported first)."""
    load_plugins()
    return dict(_FAMILIES)


def family(name: str) -> type["MethodFamily"]:
    """The family registered as ``name``, or a KeyError listing the registered ones."""
    load_plugins()
    if name not in _FAMILIES:
        raise KeyError(f"no method family {name!r} is registered (registered: {', '.join(sorted(_FAMILIES))}; "
                       "a plug-in's module goes in generator.plugins)")
    return _FAMILIES[name]


def method_config(g, method: str):
    """``generator.methods.<method>``, or a KeyError listing the methods there are."""
    if method not in g.methods:
        raise KeyError(f"generator.method={method!r} is not in generator.methods ({', '.join(g.methods)})")
    return g.methods[method]


def family_of(g, method: str) -> type["MethodFamily"]:
    """The family of ``generator.methods.<method>`` (plug-ins of ``generator.plugins`` loaded)."""
    load_plugins(g.get("plugins") or ())
    entry = method_config(g, method)
    fam = entry.get("family") if hasattr(entry, "get") else None         # a mapping (dict or DictConfig)
    if not fam:
        raise KeyError(f"generator.methods.{method}: no family key (one of {', '.join(sorted(families()))})")
    return family(str(fam))


def load_method(folder, map_location: str = "cpu", plugins: Iterable[str] = ()):
    """The trained method in ``folder`` (``<generator.out_dir>/<method>`` or a package's
    ``generator/``), loaded by its family (``method.json``; older folders are recognised by
    the family that wrote them), knowing its folder and the record of what it was built from
    (``party.provenance.attach``)."""
    from party import provenance
    from party.methods.store import read_family
    from party.names import check_name
    load_plugins(plugins)
    trained = family(read_family(folder, _FAMILIES.values())).load(folder, map_location)
    for s in [*trained.meta.get("streams", ()), *getattr(trained, "streams", ())]:   # <tokenizers>/<stream>/
        check_name(s, "stream of the trained method", str(folder))
    return provenance.attach(trained, folder)
