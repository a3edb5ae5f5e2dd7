"""Registry of named controller presets, with lazy imports so ``cacc-bench list`` stays fast.

A controller is named on the command line as ``name`` or ``name:key=value,key=value`` (options of
its config dataclass); in a comma list, a ``key=value`` item belongs to the controller before it:
``--controllers mpc:solver=ipopt,horizon=30,cacc``. The options become part of the controller's
label (``mpc[horizon=30,solver=ipopt]``), so two settings never share a leaderboard row.

Controllers from the user's own code need no edit here: ``--controllers my_laws:MyLaw`` names a
:class:`controllers.base.Controller` subclass by ``package.module:Class`` (options after a
further colon, ``my_laws:MyLaw:gain=2``; its label is ``my_laws:MyLaw[gain=2]``), and an installed
package adds names through the entry-point group :data:`ENTRY_POINT_GROUP`. Both resolve here,
in every process that runs them (:func:`resolve`), so every command and executor takes them.
"""

from __future__ import annotations

import contextlib
import dataclasses
import importlib
import importlib.util
import inspect
import re
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from envs.params import PlatoonParams
from envs.scenarios import Scenario, check_size_fits
from infra.errors import CaccBenchError, ConfigError, UnknownNameError
from infra.naming import (
    canonical_value,
    coerce_option,
    format_label,
    is_reference,
    parse_named_list,
)
from infra.plugins import (
    canonical_reference,
    entry_points,
    first_line,
    import_reference,
    load_plugin,
)
from marl.learners import LEARNERS

if TYPE_CHECKING:
    from controllers.base import Controller


@dataclass(frozen=True)
class ControllerSpec:
    """A registered controller preset.

    Attributes
    ----------
    name : str
        Registered name (what ``--controllers`` takes).
    family : str
        ``human``, ``linear``, ``mpc`` or ``marl``.
    v2v : str
        What it receives over V2V, in words.
    description : str
        One line for ``cacc-bench list``.
    target : str
        ``module:callable`` building the controller from keyword options.
    fixed : dict
        Keyword arguments always passed to the target (e.g. the MARL algorithm).
    requires : tuple of str
        Further modules it needs (``libsumo`` for the models that run inside SUMO), and
    install : str
        the command that installs them (said when one is missing).
    """

    name: str
    family: str
    v2v: str
    description: str
    target: str
    fixed: dict[str, Any] = field(default_factory=dict)
    requires: tuple[str, ...] = ()
    install: str = ""

    @property
    def available(self) -> bool:
        """Whether the implementing module and the modules it requires are present (checked
        without importing them)."""
        module = self.target.split(":", 1)[0]
        try:
            return all(importlib.util.find_spec(m) is not None
                       for m in (module, *self.requires))
        except ModuleNotFoundError:
            return False


CONTROLLERS: dict[str, ControllerSpec] = {}


def register_controller(spec: ControllerSpec) -> None:
    """Add a controller preset (registering one adds it to the parametrised tests)."""
    CONTROLLERS[spec.name] = spec


#: The entry-point group through which an installed package adds controllers, in its
#: ``pyproject.toml``: ``[project.entry-points."cacc_bench.controllers"]`` then
#: ``heard-speed = "my_laws:HeardSpeed"`` (docs/contributing.md, "Add a controller").
ENTRY_POINT_GROUP = "cacc_bench.controllers"

#: What an entry point's name may be: a plain name, as the presets' (no ``:``, ``,``, ``[``).
PLAIN_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.+-]*")

#: How to name a controller of one's own, for messages.
OWN_CONTROLLER_HINT = ("or a controller class of your own as package.module:Class "
                       "(docs/contributing.md, Add a controller)")

_PLUGINS: dict[str, ControllerSpec] = {}  # the specs of references and entry points, once built


def plugin_targets() -> dict[str, str]:
    """``name -> "package.module:Class"`` of the installed packages' controllers
    (:data:`ENTRY_POINT_GROUP`), read without importing them; a name a preset holds, or one
    that is not a plain name, is left out (:func:`plugin_conflicts` says which)."""
    return {name: target for name, target in entry_points(ENTRY_POINT_GROUP).items()
            if name not in CONTROLLERS and PLAIN_NAME.fullmatch(name)}


def plugin_conflicts() -> dict[str, str]:
    """Entry points of :data:`ENTRY_POINT_GROUP` that are not used, with why (for ``list``)."""
    out = {}
    for name, target in entry_points(ENTRY_POINT_GROUP).items():
        if name in CONTROLLERS:
            out[name] = f"{target} is not used: {name} is a built-in controller"
        elif not PLAIN_NAME.fullmatch(name):
            out[name] = f"{target} is not used: its name is not a plain name (letters, digits, -_.+)"
    return out


def _plugin_spec(name: str, target: str) -> ControllerSpec:
    """The spec of a controller class in the user's code (``name`` is the reference itself or
    an entry point's name): the class must subclass :class:`controllers.base.Controller`,
    implement its abstract methods and declare a known family; its description is its
    docstring's first line, its V2V its ``v2v`` attribute if it has one.

    Raises
    ------
    ConfigError
        One line for each way it fails (:func:`infra.plugins.import_reference`, and the above).
    """
    module = target.split(":", 1)[0]
    if target == name and module in CONTROLLERS:
        raise ConfigError(f"controller {name}: an option is written key=value ({module}:key=value); "
                          f"{module} is a built-in controller, not a module")
    return load_plugin(_PLUGINS, "controller", name, target,
                       lambda cls, who: _controller_spec(cls, who, name, target))


def _controller_spec(cls: Any, who: str, name: str, target: str) -> ControllerSpec:
    """The spec of the object ``cls`` a reference found, checked as :func:`_plugin_spec` says."""
    from controllers.base import FAMILIES, Controller

    if not (isinstance(cls, type) and issubclass(cls, Controller)):
        raise ConfigError(f"{who}: {target.split(':', 1)[1]} is not a controller class: a "
                          "controller subclasses controllers.base.Controller (docs/contributing.md, "
                          "Add a controller)")
    if inspect.isabstract(cls):
        missing = ", ".join(sorted(getattr(cls, "__abstractmethods__", ())))
        raise ConfigError(f"{who}: {cls.__name__} does not implement {missing} of "
                          "controllers.base.Controller")
    if cls.family not in FAMILIES:
        raise ConfigError(f"{who}: family {cls.family!r} is not one of {', '.join(FAMILIES)}; "
                          "set the class attribute family to one of them")
    required = _required_arguments(cls)
    if required:  # its options are keyword arguments with defaults: no default, no option
        raise ConfigError(f"{who}: {cls.__name__}() needs {', '.join(required)}; give every "
                          "argument of its constructor a default (its options are keyword "
                          "arguments with defaults, set as name:key=value)")
    doc = (cls.__doc__ or "").strip().splitlines()
    return ControllerSpec(name, cls.family, str(getattr(cls, "v2v", "what its messages() declare")),
                          doc[0] if doc else f"{cls.__name__} from {target.split(':', 1)[0]}",
                          target)


def _required_arguments(cls: type) -> list[str]:
    """The arguments ``cls()`` cannot be called without (none if its signature is unknown)."""
    try:
        params = inspect.signature(cls).parameters.values()
    except (TypeError, ValueError):
        return []
    return [p.name for p in params if p.default is p.empty
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]


def canonical_name(name: str) -> str:
    """The one spelling of a controller's name: a reference names its class where it is
    defined (:func:`infra.plugins.canonical_reference`; ``safe:`` kept before it), so one class
    is one leaderboard row; any other name as given. Imports a referenced module (its failures
    are :class:`ConfigError` lines)."""
    inner = name.removeprefix(SAFE_PREFIX)
    if (not is_reference(inner) or inner in CONTROLLERS  # a preset named module:attr (sumo:acc)
            or inner.startswith(SAFE_PREFIX)):  # safe:safe:x, refused by the filter's own rule
        return name
    spec = _plugin_spec(inner, inner)
    canonical = canonical_reference(_factory(spec), inner)
    if canonical != inner:
        _PLUGINS.setdefault(canonical, dataclasses.replace(spec, name=canonical, target=canonical))
    return name[:len(name) - len(inner)] + canonical


for _spec_args in (  # name, family, V2V, description, target
    ("ovm", "human", "none",
     "optimal velocity model, (alpha, beta) = (0.5, 0.5): the human driver (MARL action 3)",
     "controllers.ovm:OVMController"),
    ("duty", "human", "none",
     "OVM action 3 every k-th step, action 2 otherwise (k=K; default: best k on the "
     "validation seeds): what a trivial schedule of the MARL actions achieves",
     "controllers.duty:DutyController"),
    ("acc", "linear", "none",
     "constant time-gap ACC, u = kp e + kd de/dt (Ploeg's law without feedforward)",
     "controllers.linear:ACCController"),
    ("cacc", "linear", "predecessor's commanded acceleration (1 float)",
     "Ploeg's CACC: constant time gap with the predecessor's command as feedforward",
     "controllers.linear:CACCController"),
    ("mpc", "mpc", "predecessor's assumed speed plan with its time stamp (H+2 floats)",
     "energy-aware distributed MPC with the fitted power model (CasADi)",
     "controllers.mpc:DMPCController"),
    ("mpc-qp", "mpc", "predecessor's assumed speed plan with its time stamp (H+2 floats)",
     "quadratic distributed MPC without energy term (OSQP)",
     "controllers.mpc_qp:QPDMPCController"),
    ("cmpc", "mpc", "full state of the platoon (centralised)",
     "centralised MPC of the whole platoon with full information (cvxpy)",
     "controllers.cmpc:CentralisedMPCController"),
    ("openacc-real", "data", "none (real ACC cars)",
     "the recorded ACC followers of an OpenACC window (openacc-* scenarios only; paper Table III)",
     "controllers.replay:RealACCRecord"),
    ("idm", "human", "none",
     "Intelligent Driver Model with the human seats' noise and delay: on ring-v1 it is the "
     "all-human ring",
     "controllers.idm:IDMController"),
    ("followerstopper", "linear", "none",
     "Stern et al. 2018 FollowerStopper: a commanded speed from gap and closing speed, "
     "capped at the set speed U (default: the scenario's target speed)",
     "controllers.wave_dampers:FollowerStopperController"),
    ("pi-saturation", "linear", "none",
     "Stern et al. 2018 PI controller with saturation: tracks its own 38 s mean speed, "
     "blended with the predecessor's speed at short gaps",
     "controllers.wave_dampers:PISaturationController"),
):
    register_controller(ControllerSpec(*_spec_args))

for _learner in LEARNERS.values():  # every learner's policy, from the one learner registry
    register_controller(ControllerSpec(_learner.name, "marl", _learner.v2v, _learner.description,
                                       "controllers.policy:PolicyController",
                                       fixed={"algo": _learner.name}))

#: The module of the models that drive inside SUMO (``--simulator sumo`` only).
SIMULATOR_MODELS_MODULE = "controllers.sumo_models"
for _name, _v2v, _description in (  # controllers others wrote, run inside SUMO as references
    ("sumo:acc", "none",
     "SUMO's ACC car-following model (Milanes and Shladover 2014), inside SUMO"),
    ("sumo:cacc", "none through the harness (SUMO's model reads its leader inside SUMO)",
     "SUMO's CACC car-following model (Milanes and Shladover 2014, Xiao et al. 2017), inside "
     "SUMO"),
    ("plexe:ploeg", "predecessor's speed and commanded acceleration (2 floats)",
     "Plexe's Ploeg CACC (SUMO's CC model, Ploeg's gains, 2 m standstill), inside SUMO"),
    ("plexe:path", "predecessor's and leader's speed and commanded acceleration (2 + 2 floats)",
     "Plexe's PATH CACC (SUMO's CC model, Rajamani's constant spacing), inside SUMO"),
):
    register_controller(ControllerSpec(_name, "linear", _v2v, _description,
                                       f"{SIMULATOR_MODELS_MODULE}:SumoModelController",
                                       fixed={"model": _name}, requires=("libsumo", "sumo"),
                                       install="pip install -e '.[sumo]'"))


def runs_inside_simulator(spec: ControllerSpec) -> bool:
    """Whether the controller is a model that drives inside SUMO (``sumo:acc``,
    ``plexe:ploeg``, ...): it runs with ``--simulator sumo`` only and has no commands of its own
    for the harness."""
    return spec.target.startswith(SIMULATOR_MODELS_MODULE + ":")


#: Controllers of ``cacc-bench run`` when none are named (those available in this install):
#: the human baseline and its duty schedule, the linear laws, the quadratic MPC and the paper's
#: method, all quick.
DEFAULT_CONTROLLERS: tuple[str, ...] = ("ovm", "duty", "acc", "cacc", "mpc-qp", "bdc")


def default_controllers() -> list[str]:
    """The default controllers that are available in this install."""
    return [name for name in DEFAULT_CONTROLLERS if CONTROLLERS[name].available]


def mixed_traffic_controllers(ring: bool = False) -> list[str]:
    """Names of the available controllers that drive strings with human drivers (with ``ring``:
    that also run without a scripted leader), read from their classes' ``drives_mixed`` and
    ``needs_leader``, or a class's ``traits(**fixed)`` (imports their modules: for messages,
    not for ``list``)."""
    out = []
    for spec in available_controllers():
        cls = _factory(spec)
        traits = getattr(cls, "traits", None)  # one class for several (the learned policies)
        cls = cls if traits is None else traits(**spec.fixed)
        if ring and getattr(cls, "needs_leader", False):
            continue
        if not ring and not getattr(cls, "drives_mixed", True):
            continue
        out.append(spec.name)
    return out


def available_controllers() -> list[ControllerSpec]:
    """Registered controllers whose implementation is present, in registration order, then
    the installed packages' (:data:`ENTRY_POINT_GROUP`; one that fails to load is left out:
    naming it says why)."""
    out = [s for s in CONTROLLERS.values() if s.available]
    for name, target in plugin_targets().items():
        try:
            out.append(_plugin_spec(name, target))
        except CaccBenchError:
            continue
    return out


#: Prefix of a filtered controller: ``safe:<controller>`` wraps a registered controller in the
#: safety filter (:mod:`controllers.safety_filter`); its options are the wrapped one's.
SAFE_PREFIX = "safe:"


def parse_controller_list(text: str) -> list[tuple[str, dict[str, str]]]:
    """Parse ``"mpc:solver=ipopt,horizon=30,cacc"`` into ``[("mpc", {...}), ("cacc", {})]``;
    ``safe:bdc:scenario=catchup-v1`` is the controller ``safe:bdc`` with its option; a
    ``package.module:Class`` reference is imported and checked here and comes back in its
    canonical spelling (:func:`canonical_name`)."""
    return [(canonical_name(name), options) for name, options
            in parse_named_list(text, "controller", name_prefixes=(SAFE_PREFIX,))]


def controller_label(name: str, options: dict[str, Any]) -> str:
    """Leaderboard label: the name, plus its non-default options in brackets, sorted (an option
    given at its default value adds nothing: ``ovm:alpha=0.5`` is ``ovm``); a reference in its
    canonical spelling (``my_laws:MyLaw[gain=2]``)."""
    return format_label(canonical_name(name), canonical_options(name, options))


def _safe_spec(name: str) -> ControllerSpec:
    """The spec of ``safe:<controller>``: the wrapped controller's family and V2V, built by
    :class:`controllers.safety_filter.SafetyFilter`."""
    inner = name[len(SAFE_PREFIX):].strip()
    if not inner:
        raise ConfigError(f"{name!r} names no controller to filter; write {SAFE_PREFIX}<controller>, "
                          f"e.g. {SAFE_PREFIX}cacc or {SAFE_PREFIX}bdc:scenario=catchup-v1")
    if inner.startswith(SAFE_PREFIX):
        raise ConfigError(f"{name!r}: the safety filter wraps a controller once (filtering a "
                          f"filtered command changes nothing); write {SAFE_PREFIX}"
                          f"{inner.removeprefix(SAFE_PREFIX).lstrip(':')}")
    spec = resolve(inner)
    if runs_inside_simulator(spec):
        raise ConfigError(f"{name!r}: {inner} is a model that drives inside SUMO; the harness "
                          "never sees its commands, so the safety filter has none to correct")
    if spec.family == "data":
        raise ConfigError(f"{name!r}: {inner} is a recorded platoon, not a control law; it has no "
                          "commands for the safety filter to correct")
    return ControllerSpec(name, spec.family, spec.v2v,
                          f"{inner} behind the worst-case-braking safety filter",
                          "controllers.safety_filter:SafetyFilter", fixed={"inner": inner})


def _factory(spec: ControllerSpec) -> Callable[..., Any]:
    if spec.name in _PLUGINS:  # the user's code: its failures are one line
        return import_reference(spec.target, f"controller {spec.name}")
    module_name, attr = spec.target.split(":", 1)
    return getattr(importlib.import_module(module_name), attr)


def batch_invariant(name: str) -> bool:
    """Whether the registered controller declares ``batch_invariant`` (the harness may step
    its seeds together; see :class:`controllers.base.Controller`); a controller class with a
    ``batch_invariant_probe(**fixed)`` decides on this machine (the learned policies)."""
    spec = resolve(name)
    try:
        factory = _factory(spec)
    except ImportError:
        return False
    probe = getattr(factory, "batch_invariant_probe", None)
    if probe is not None:
        return bool(probe(**spec.fixed))
    return bool(getattr(factory, "batch_invariant", False))


def controller_options(name: str) -> dict[str, Any]:
    """The options a registered controller takes, with their defaults (its config dataclass's
    fields, or its constructor's keyword arguments)."""
    spec = resolve(name)
    factory = _factory(spec)
    options_of = getattr(factory, "options_of", None)  # a wrapper's, a learned policy's
    if options_of is not None:
        return dict(options_of(**spec.fixed))
    config_cls = getattr(factory, "config_cls", None)
    if config_cls is not None and dataclasses.is_dataclass(config_cls):
        return {f.name: (f.default if f.default is not dataclasses.MISSING
                         else f.default_factory())  # type: ignore[misc,operator]
                for f in dataclasses.fields(config_cls) if f.init}
    params = inspect.signature(factory).parameters.values()
    return {p.name: p.default for p in params
            if p.kind is p.POSITIONAL_OR_KEYWORD and p.name not in spec.fixed
            and p.default is not p.empty}


def option_types(name: str) -> dict[str, Any]:
    """The type of each option of a registered controller, for :func:`infra.naming.coerce_option`:
    its default's type, or for a default of None its annotation (the config dataclass's field,
    the constructor's argument; ``safe:`` adds the filter's)."""
    spec = resolve(name)
    factory: Any = _factory(spec)
    if name.startswith(SAFE_PREFIX):  # the filter's own options (prefixed), then the inner's
        hints = {factory.option_prefix + k: v
                 for k, v in typing.get_type_hints(factory.filter_config_cls).items()}
        hints.update(option_types(spec.fixed["inner"]))
    else:
        config_cls = getattr(factory, "config_cls", None)
        try:
            hints = typing.get_type_hints(factory.__init__ if config_cls is None else config_cls)
        except Exception:  # noqa: BLE001 - annotations that do not evaluate: the defaults' types
            hints = {}
    return {k: hints.get(k, str) if d is None else type(d)
            for k, d in controller_options(name).items()}


def canonical_options(name: str, options: dict[str, Any]) -> dict[str, Any]:
    """``options`` in their canonical spelling (:func:`infra.naming.canonical_value` of the
    typed value: ``kp=2.0`` is ``kp=2``, a folder its resolved path), without those given at
    their default value (``ovm:alpha=0.5`` is ``ovm``). Unregistered names, options the
    controller does not take and values it will refuse (with its own message) stay as given."""
    if not options:
        return dict(options)
    try:
        defaults, types = controller_options(name), option_types(name)
    except CaccBenchError:
        return dict(options)
    out = {}
    for key, value in options.items():
        try:
            typed = coerce_option(value, types[key], key, name) if key in types else value
        except ConfigError:
            typed = value
        if key not in defaults or typed != defaults[key]:
            out[key] = canonical_value(typed)
    return out


def resolve(name: str) -> ControllerSpec:
    """The spec of a registered and available controller (or of ``safe:<controller>``), or a
    clear error."""
    if name.startswith(SAFE_PREFIX):
        return _safe_spec(name)
    spec = CONTROLLERS.get(name)
    if spec is None and is_reference(name):  # a class of the user's: package.module:Class
        return _plugin_spec(name, name)
    if spec is None and name in plugin_targets():  # an installed package's entry point
        return _plugin_spec(name, plugin_targets()[name])
    if spec is not None and not spec.available and spec.install:
        raise ConfigError(f"{name} needs {', '.join(spec.requires)}; install it with: "
                          f"{spec.install}")
    if spec is None or not spec.available:
        raise UnknownNameError("controller", name, [s.name for s in available_controllers()],
                               hint=OWN_CONTROLLER_HINT)
    return spec


def make_controller(name: str, /, **options: Any) -> Any:
    """Build a controller by registered name with keyword options (strings are coerced).

    An option the controller does not take is a :class:`ConfigError` naming the ones it does
    (the one rule for every controller, whether its options are a config dataclass's fields
    or its constructor's keyword arguments). A class of the user's code that fails to build
    is one :class:`ConfigError` line too (its error's first line), and one that keeps the base
    class's name is named by its reference in the harness's messages."""
    spec = resolve(name)
    plugin = spec.target in _PLUGINS or spec.name in _PLUGINS
    if options:
        known = controller_options(name)
        unknown = [k for k in options if k not in known]
        if unknown:
            raise ConfigError(f"{name} has no option {unknown[0]!r}; its options are: "
                              f"{', '.join(sorted(known)) or 'none'}")
        if plugin:  # the user's class takes them typed
            types = option_types(name)
            options = {k: coerce_option(v, types[k], k, name) for k, v in options.items()}
    if not plugin:
        return _factory(spec)(**spec.fixed, **options)
    from controllers.base import Controller

    try:
        ctrl = _factory(spec)(**spec.fixed, **options)
    except CaccBenchError:
        raise
    except Exception as exc:  # noqa: BLE001 - the user's constructor: any error is one line
        raise ConfigError(f"controller {name}: building it failed ({first_line(exc)})") from None
    if getattr(ctrl, "name", None) == Controller.name:
        with contextlib.suppress(AttributeError):  # a read-only name stays as it is
            ctrl.name = name
    return ctrl


def check_fits(controller: Controller, scenario: Scenario, n_vehicles: int,
               params: PlatoonParams | None = None) -> None:
    """Refuse, before any work, a setting ``controller`` cannot run (:class:`ConfigError` naming
    what works): a string with human drivers for a controller that cannot drive one, a ring for
    one that needs a leader, a string with no automated vehicle for anything but a human-driver
    model, vehicle classes for a recorded platoon (``openacc-real``: they would relabel the
    recording); then the controller's own :meth:`Controller.preflight`. Every sweep calls this for
    each setting before its first run."""
    check_size_fits(scenario, n_vehicles)
    if params is not None:  # vehicle classes and a run-wide lag at once are refused
        scenario.vehicle_arrays(n_vehicles, params)
    arrangement = scenario.arrangement(n_vehicles)
    where = f"{scenario.label or scenario.id} with N = {n_vehicles}"
    if arrangement.n_automated == 0 and controller.family != "human":
        raise ConfigError(
            f"{controller.name} is an automated controller and {where} has no automated "
            "vehicle; its all-human baseline is a human-driver model (--controllers idm), or "
            "give the scenario automated vehicles (cav_fraction=0.25, cavs=1, humans=2+5)")
    if not arrangement.homogeneous and not controller.drives_mixed:
        raise ConfigError(
            f"{controller.name} cannot run on {where}: it has human drivers "
            f"({len(arrangement.automated) - arrangement.n_automated} of "
            f"{len(arrangement.automated)}) and {controller.name} was made for a string of "
            "automated vehicles only; the controllers that run on mixed strings: "
            f"{', '.join(mixed_traffic_controllers())}")
    classes = scenario.options.get("classes") or scenario.options.get("class_mix")
    if classes and getattr(controller, "recorded", None) is not None:
        raise ConfigError(
            f"{controller.name} is a recorded platoon, the vehicles as they drove; vehicle "
            f"classes ({classes}) would label the recording as vehicles it is not: name "
            f"{scenario.id} without classes or class_mix")
    if scenario.ring and controller.needs_leader:
        raise ConfigError(
            f"{controller.name} needs a scripted leader and {where} is a ring road without one; "
            "the controllers that run on the ring: "
            f"{', '.join(mixed_traffic_controllers(ring=True))}")
    controller.preflight(scenario, n_vehicles, params)
