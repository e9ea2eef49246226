"""Validated, frozen records: the schema language of every kind's config.

A config class is a :class:`Record` subclass whose annotated class attributes are its fields::

    class OspaSpec(Record):
        cutoff_m: Float = 1000.0
        order: Float = Field(default=2.0, ge=1.0)

        _c = field_validator("cutoff_m")(positive)

:meth:`Record.model_validate` (and the constructor) turns parsed YAML into an instance or raises
:class:`ValidationError` listing *every* problem with its location. The rules, the same for
every field:

- **types are strict**: a ``float`` field takes a number (an ``int`` becomes a ``float``; no
  booleans, no strings, no inf or NaN, a magnitude at most ``MAX_MAGNITUDE``), ``int`` an
  integer (no booleans, no ``2.0``), ``str`` and ``bool`` only themselves; ``Literal[...]``
  one of its values; ``tuple[X, ...]`` a list or tuple of ``X`` (kept as a tuple); ``tuple[X,
  Y]`` exactly two; ``dict[str, X]`` a mapping; ``X | None`` ``None`` or an ``X``; ``Any``
  anything; a record a mapping of its fields (or an instance, taken as it is);
- **unknown keys are errors** (usually typos); a field without a default is required;
- constraints (:func:`Field`: ``ge``/``gt``/``le``/``lt`` on numbers, ``min_length``/
  ``max_length`` on tuples and strings, ``pattern`` on strings) are checked once the value has
  its type; a container's length only once each of its items is valid (a bad item is the cause:
  the length is reported only when it is wrong by itself);
- then the field's checks run (:class:`AfterValidator` in its ``Annotated`` type, then the
  :func:`field_validator`\\ s naming it, in class order): a ``ValueError`` they raise is the
  problem, at the field's location (a :class:`Placed` problem at the location plus its
  ``where``, with its own ``type``);
- a record's own :func:`model_validator` runs when all its fields are valid;
- defaults are not validated (they are the author's, not the user's).

Records are immutable, compared and hashed by value, and pickle by value.
:meth:`Record.model_dump` gives them back as plain data (``mode="json"``: tuples as lists).

Built here rather than taken from a validation library: a config is a few dozen small classes,
and :mod:`covnet.cli.app` loads one on every command; building a general library's validators cost
``covnet run`` about a fifth of its start-up.  This module only compiles a class's validator
when the class is first validated, and imports nothing beyond ``re`` and ``typing``.
"""

from __future__ import annotations

import math
import re
import types
from collections.abc import Callable, Iterator, Mapping
from typing import (
    Annotated,
    Any,
    ClassVar,
    Literal,
    Union,
    dataclass_transform,
    get_args,
    get_origin,
    get_type_hints,
)

__all__ = [
    "AfterValidator",
    "Field",
    "FieldInfo",
    "Placed",
    "Record",
    "ValidationError",
    "field_validator",
    "model_validator",
]

Loc = tuple[int | str, ...]


class _Missing:
    def __repr__(self) -> str:
        return "<required>"


MISSING: Any = _Missing()


class FieldInfo:
    """A field's default (or :data:`MISSING`), default factory and constraints; given as a
    field's default (``x: Int = Field(default=1, ge=0)``) or in its type
    (``Annotated[Str, Field(min_length=1)]``)."""

    __slots__ = ("default", "default_factory", "constraints", "owner", "name")

    def __init__(
        self,
        default: Any = MISSING,
        default_factory: Callable[[], Any] | None = None,
        constraints: dict[str, Any] | None = None,
    ) -> None:
        self.default = default
        self.default_factory = default_factory
        self.constraints = constraints or {}
        self.owner: type[Record] | None = None
        self.name = ""

    def is_required(self) -> bool:
        return self.default is MISSING and self.default_factory is None

    def get_default(self, call_default_factory: bool = False) -> Any:
        if self.default_factory is not None:
            return self.default_factory() if call_default_factory else None
        return None if self.default is MISSING else self.default

    @property
    def annotation(self) -> Any:
        """The field's type (its hint, evaluated)."""
        assert self.owner is not None
        return self.owner._hints()[self.name]

    def __repr__(self) -> str:
        return f"FieldInfo(default={self.default!r}, constraints={self.constraints!r})"


def Field(  # noqa: N802 - it reads as a declaration, like the dataclass field specifier
    default: Any = MISSING,
    *,
    default_factory: Callable[[], Any] | None = None,
    ge: float | None = None,
    gt: float | None = None,
    le: float | None = None,
    lt: float | None = None,
    min_length: int | None = None,
    max_length: int | None = None,
    pattern: str | None = None,
) -> Any:
    """A field's default and constraints (module docstring)."""
    given = {
        "min_length": min_length,
        "max_length": max_length,
        "pattern": pattern,
        "ge": ge,
        "gt": gt,
        "le": le,
        "lt": lt,
    }
    return FieldInfo(default, default_factory, {k: v for k, v in given.items() if v is not None})


class AfterValidator:
    """A check in a field's type, ``Annotated[T, AfterValidator(fn)]``: ``fn(value)`` returns
    the value (or a replacement) or raises ``ValueError``."""

    __slots__ = ("func",)

    def __init__(self, func: Callable[[Any], Any]) -> None:
        self.func = func


class _FieldCheck:
    __slots__ = ("names", "func")

    def __init__(self, names: tuple[str, ...], func: Any) -> None:
        self.names = names
        self.func = func  # a function of the value, or a classmethod of (cls, value)

    def __call__(self, cls: type, value: Any) -> Any:
        if isinstance(self.func, classmethod):
            return self.func.__func__(cls, value)
        return self.func(value)


def field_validator(*names: str) -> Callable[[Any], Any]:
    """Decorate a check of the fields ``names`` (a function of the value, or a classmethod of
    ``(cls, value)``): it returns the value or raises ``ValueError``.  Also usable on a shared
    function: ``_pos = field_validator("a", "b")(positive)``."""

    def mark(func: Any) -> Any:
        return _FieldCheck(names, func)

    return mark


class _RecordCheck:
    __slots__ = ("func",)

    def __init__(self, func: Callable[[Any], Any]) -> None:
        self.func = func


def model_validator(*, mode: Literal["after"]) -> Callable[[Any], Any]:
    """Decorate a method ``check(self) -> self`` that runs once every field of the record is
    valid (``mode="after"``, the only mode); it raises ``ValueError`` for a problem."""
    if mode != "after":
        raise ValueError("only mode='after' is supported")

    def mark(func: Callable[[Any], Any]) -> Any:
        return _RecordCheck(func)

    return mark


class ValidationError(ValueError):
    """Every problem found in one validation: :meth:`errors` gives them as dicts with ``loc``
    (the path: keys and indices), ``type`` (``missing``, ``extra_forbidden``, ``value_error``,
    ``float_type``, ...), ``msg`` and ``input``."""

    def __init__(self, title: str, errors: list[dict[str, Any]]) -> None:
        self.title = title
        self._errors = errors
        lines = "\n".join(f"  {'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors)
        super().__init__(f"{len(errors)} problem(s) in {title}:\n{lines}")

    def errors(self) -> list[dict[str, Any]]:
        return list(self._errors)


class Placed(ValueError):
    """A check's problem at a place inside the value it checks: raised by a field's check, it is
    reported at the field's location plus ``where`` (keys and indices: ``(1, "id")`` is the
    second item's ``id``), with the error ``type`` ``kind`` (``value_error`` unless a caller
    needs to tell it apart: :func:`covnet.config.unique_ids`' ``duplicate_id``)."""

    def __init__(self, where: Loc, text: str, kind: str = "value_error") -> None:
        super().__init__(text)
        self.where, self.text, self.kind = tuple(where), text, kind


class _Bad:
    """The result of a value that failed (its problems are in the error list)."""


BAD: Any = _Bad()
Errors = list[dict[str, Any]]
Check = Callable[[Any, Loc, Errors], Any]


def _err(errors: Errors, loc: Loc, kind: str, msg: str, value: Any) -> Any:
    errors.append({"loc": loc, "type": kind, "msg": msg, "input": value})
    return BAD


def _num(x: float) -> str:
    return str(int(x)) if isinstance(x, float) and x.is_integer() else str(x)


# ---------------------------------------------------------------------------------------------
# scalar checks
# ---------------------------------------------------------------------------------------------


#: the largest magnitude a float field takes: a standard deviation of 1e308 m passed the
#: finite check, then overflowed in the run (its square, the filter's products) and ended in
#: a traceback; 1e15 leaves every physical quantity of a config (metres, seconds, variances,
#: weights) room, and its fourth power is still far from an overflow
MAX_MAGNITUDE = 1e15


def _float(v: Any, loc: Loc, errors: Errors) -> Any:
    if isinstance(v, bool) or not isinstance(v, int | float):
        return _err(errors, loc, "float_type", "Input should be a valid number", v)
    try:
        v = float(v)
    except OverflowError:  # an integer beyond a float's range
        v = math.inf
    if not math.isfinite(v):
        return _err(errors, loc, "finite_number", "Input should be a finite number", v)
    if abs(v) > MAX_MAGNITUDE:
        return _err(
            errors, loc, "finite_number",
            f"Input should be a number of magnitude at most {MAX_MAGNITUDE:g} (the run squares "
            "and multiplies it: beyond, its arithmetic overflows)", v,
        )  # fmt: skip
    return v + 0.0  # -0.0 as 0.0: one number, one hash (its sign changed the config's hash)


def _int(v: Any, loc: Loc, errors: Errors) -> Any:
    if isinstance(v, bool) or not isinstance(v, int):
        return _err(errors, loc, "int_type", "Input should be a valid integer", v)
    return v


def _str(v: Any, loc: Loc, errors: Errors) -> Any:
    if not isinstance(v, str):
        return _err(errors, loc, "string_type", "Input should be a valid string", v)
    return v


def _bool(v: Any, loc: Loc, errors: Errors) -> Any:
    if not isinstance(v, bool):
        return _err(errors, loc, "bool_type", "Input should be a valid boolean", v)
    return v


def _any(v: Any, loc: Loc, errors: Errors) -> Any:
    return v


_SCALARS: dict[Any, Check] = {
    float: _float,
    int: _int,
    str: _str,
    bool: _bool,
    Any: _any,
}


def _literal(choices: tuple[Any, ...]) -> Check:
    shown = [repr(c) for c in choices]
    text = shown[0] if len(shown) == 1 else ", ".join(shown[:-1]) + " or " + shown[-1]

    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        for c in choices:
            if v == c and type(v) is type(c):
                return c
        return _err(errors, loc, "literal_error", f"Input should be {text}", v)

    return check


def _optional(inner: Check) -> Check:
    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        return None if v is None else inner(v, loc, errors)

    return check


def _is_sequence(v: Any) -> bool:
    return isinstance(v, list | tuple)


def _tuple_of(item: Check) -> Check:
    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        if not _is_sequence(v):
            return _err(errors, loc, "tuple_type", "Input should be a valid tuple", v)
        out = [item(x, (*loc, i), errors) for i, x in enumerate(v)]
        return BAD if any(x is BAD for x in out) else tuple(out)

    return check


def _fixed_tuple(items: tuple[Check, ...]) -> Check:
    n = len(items)

    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        if not _is_sequence(v):
            return _err(errors, loc, "tuple_type", "Input should be a valid tuple", v)
        if len(v) > n:
            msg = f"Tuple should have at most {n} items after validation, not {len(v)}"
            return _err(errors, loc, "too_long", msg, v)
        out = []
        for i, item in enumerate(items):
            if i >= len(v):
                out.append(_err(errors, (*loc, i), "missing", "Field required", v))
            else:
                out.append(item(v[i], (*loc, i), errors))
        return BAD if any(x is BAD for x in out) else tuple(out)

    return check


def _dict_of(key: Check, value: Check) -> Check:
    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        if not isinstance(v, Mapping):
            return _err(errors, loc, "dict_type", "Input should be a valid dictionary", v)
        out = {}
        bad = False
        for k, x in v.items():
            kk = key(k, (*loc, k), errors)
            xx = value(x, (*loc, k), errors)
            bad = bad or kk is BAD or xx is BAD
            out[kk] = xx
        return BAD if bad else out

    return check


def _constrained(inner: Check, c: Mapping[str, Any]) -> Check:
    """``inner``, then the constraints ``c`` on its valid, non-None result."""

    def check(raw: Any, loc: Loc, errors: Errors) -> Any:
        v = inner(raw, loc, errors)
        if v is BAD or v is None:
            return v
        return _within(v, c, loc, errors, raw)

    return check


def _within(v: Any, c: Mapping[str, Any], loc: Loc, errors: Errors, raw: Any) -> Any:
    """``v`` if it meets the constraints ``c``, else the problem (reported with the input
    ``raw``)."""
    if isinstance(v, str | tuple):
        noun = ("String", "character") if isinstance(v, str) else ("Tuple", "item")
        after = "" if isinstance(v, str) else " after validation"
        n = len(v)
        lo, hi = c.get("min_length"), c.get("max_length")
        if lo is not None and lo == hi and n != lo:  # a fixed length: not "at least"
            what = noun[1] + ("" if lo == 1 else "s")
            tail = "" if isinstance(v, str) else f", not {n}"
            msg = f"{noun[0]} should have exactly {lo} {what}{after}{tail}"
            return _err(errors, loc, "too_short" if n < lo else "too_long", msg, raw)
        if lo is not None and n < lo:
            what = noun[1] + ("" if lo == 1 else "s")
            tail = "" if isinstance(v, str) else f", not {n}"
            msg = f"{noun[0]} should have at least {lo} {what}{after}{tail}"
            return _err(errors, loc, "too_short", msg, raw)
        if hi is not None and n > hi:
            what = noun[1] + ("" if hi == 1 else "s")
            tail = "" if isinstance(v, str) else f", not {n}"
            msg = f"{noun[0]} should have at most {hi} {what}{after}{tail}"
            return _err(errors, loc, "too_long", msg, raw)
        pattern = c.get("pattern")
        if pattern is not None and isinstance(v, str) and re.search(pattern, v) is None:
            msg = f"String should match pattern '{pattern}'"
            return _err(errors, loc, "string_pattern_mismatch", msg, raw)
        return v
    for name, ok, text in (
        ("gt", lambda a, b: a > b, "greater than"),
        ("ge", lambda a, b: a >= b, "greater than or equal to"),
        ("lt", lambda a, b: a < b, "less than"),
        ("le", lambda a, b: a <= b, "less than or equal to"),
    ):
        bound = c.get(name)
        if bound is not None and not ok(v, bound):
            return _err(errors, loc, name, f"Input should be {text} {_num(bound)}", raw)
    return v


def _after(inner: Check, funcs: tuple[Callable[[Any], Any], ...]) -> Check:
    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        v = inner(v, loc, errors)
        if v is BAD:
            return v
        for f in funcs:
            try:
                v = f(v)
            except ValueError as exc:
                return _value_error(errors, loc, exc, v)
        return v

    return check


def _value_error(errors: Errors, loc: Loc, exc: ValueError, value: Any) -> Any:
    if isinstance(exc, Placed):
        return _err(errors, (*loc, *exc.where), exc.kind, exc.text, value)
    return _err(errors, loc, "value_error", str(exc), value)


def _record(cls: type[Record]) -> Check:
    def check(v: Any, loc: Loc, errors: Errors) -> Any:
        if isinstance(v, cls):
            return v
        if not isinstance(v, Mapping):
            msg = f"Input should be a valid dictionary or instance of {cls.__name__}"
            return _err(errors, loc, "model_type", msg, v)
        return cls._build(v, loc, errors)

    return check


def _compile(tp: Any) -> Check:
    """The check of a value of type ``tp`` (module docstring)."""
    if tp in _SCALARS:
        return _SCALARS[tp]
    if isinstance(tp, type) and issubclass(tp, Record):
        return _record(tp)
    origin, args = get_origin(tp), get_args(tp)
    if origin is Annotated:
        check = _compile(args[0])
        constraints: dict[str, Any] = {}
        funcs: list[Callable[[Any], Any]] = []
        for meta in args[1:]:
            if isinstance(meta, FieldInfo):
                constraints.update(meta.constraints)
            elif isinstance(meta, AfterValidator):
                funcs.append(meta.func)
        if constraints:
            check = _constrained(check, constraints)
        return _after(check, tuple(funcs)) if funcs else check
    if origin is Literal:
        return _literal(args)
    if origin in (Union, types.UnionType):
        arms = [a for a in args if a is not type(None)]
        if len(arms) != 1 or len(args) != 2:
            raise TypeError(f"records support X | None unions only, not {tp!r}")
        return _optional(_compile(arms[0]))
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return _tuple_of(_compile(args[0]))
        return _fixed_tuple(tuple(_compile(a) for a in args))
    if origin is dict:
        return _dict_of(_compile(args[0]), _compile(args[1]))
    raise TypeError(f"records do not support the type {tp!r}")


# ---------------------------------------------------------------------------------------------
# the record
# ---------------------------------------------------------------------------------------------


class _Spec:
    """A record class's compiled validator: per field its check, field checks and default."""

    def __init__(self, cls: type[Record]) -> None:
        hints = cls._hints()
        checks = _collect(cls, _FieldCheck)
        self.fields: list[tuple[str, FieldInfo, Check, tuple[_FieldCheck, ...]]] = []
        for name, info in cls.model_fields.items():
            check = _compile(hints[name])
            if info.constraints:
                check = _constrained(check, info.constraints)
            own = tuple(c for c in checks if name in c.names)
            self.fields.append((name, info, check, own))
        self.record_checks = tuple(c.func for c in _collect(cls, _RecordCheck))


def _collect(cls: type, kind: type) -> list[Any]:
    """The ``kind`` markers in ``cls``'s namespace and its bases' (bases first; a subclass's
    marker replaces its base's of the same name)."""
    found: dict[str, Any] = {}
    for klass in reversed(cls.__mro__):
        found.update((k, v) for k, v in vars(klass).items() if isinstance(v, kind))
    return list(found.values())


@dataclass_transform(kw_only_default=True, frozen_default=True, field_specifiers=(Field,))
class Record:
    """A validated, frozen record (module docstring)."""

    model_fields: ClassVar[dict[str, FieldInfo]] = {}
    _spec: ClassVar[_Spec | None] = None
    _hint_cache: ClassVar[dict[str, Any] | None] = None

    def __init_subclass__(cls, **kwargs: Any) -> None:
        super().__init_subclass__(**kwargs)
        fields: dict[str, FieldInfo] = {}
        for base in reversed(cls.__mro__[1:]):
            if issubclass(base, Record):
                fields.update(base.model_fields)
        for name, hint in cls.__dict__.get("__annotations__", {}).items():
            if "ClassVar" in str(hint):
                continue
            value = cls.__dict__.get(name, MISSING)
            info = value if isinstance(value, FieldInfo) else FieldInfo(value)
            if isinstance(value, FieldInfo):
                delattr(cls, name)
            info.owner, info.name = cls, name
            fields[name] = info
        cls.model_fields = fields
        cls._spec = None
        cls._hint_cache = None

    # -- construction -----------------------------------------------------------------------

    def __init__(self, **data: Any) -> None:
        errors: Errors = []
        built = type(self)._build(data, (), errors, into=self)
        if built is BAD:
            raise ValidationError(type(self).__name__, errors)

    @classmethod
    def model_validate(cls, data: Any) -> Any:
        """An instance from ``data`` (a mapping, or an instance taken as it is), or
        :class:`ValidationError` with every problem."""
        errors: Errors = []
        out = _record(cls)(data, (), errors)
        if out is BAD:
            raise ValidationError(cls.__name__, errors)
        return out

    @classmethod
    def _hints(cls) -> dict[str, Any]:
        if cls.__dict__.get("_hint_cache") is None:
            cls._hint_cache = get_type_hints(cls, include_extras=True)
        hints = cls.__dict__["_hint_cache"]
        assert hints is not None
        return hints

    @classmethod
    def _build(
        cls, data: Mapping[str, Any], loc: Loc, errors: Errors, into: Record | None = None
    ) -> Any:
        spec = cls.__dict__.get("_spec")
        if spec is None:
            spec = cls._spec = _Spec(cls)
        values: dict[str, Any] = {}
        failed = False
        for name, info, check, own in spec.fields:
            if name not in data:
                if info.is_required():
                    _err(errors, (*loc, name), "missing", "Field required", data)
                    failed = True
                else:
                    values[name] = info.get_default(call_default_factory=True)
                continue
            v = check(data[name], (*loc, name), errors)
            for c in own if v is not BAD else ():
                try:
                    v = c(cls, v)
                except ValueError as exc:
                    v = _value_error(errors, (*loc, name), exc, v)
                    break
            failed = failed or v is BAD
            values[name] = v
        for key in data:
            if key not in cls.model_fields:
                msg = "Extra inputs are not permitted"
                _err(errors, (*loc, key), "extra_forbidden", msg, data[key])
                failed = True
        if failed:
            return BAD
        obj = object.__new__(cls) if into is None else into
        obj.__dict__.update(values)
        obj.__dict__["__fields_set__"] = frozenset(k for k in data if k in cls.model_fields)
        for f in spec.record_checks:
            try:
                f(obj)
            except ValueError as exc:
                return _value_error(errors, loc, exc, data)
        return obj

    # -- reading ------------------------------------------------------------------------------

    @property
    def model_fields_set(self) -> frozenset[str]:
        """The fields the input gave (the others hold their defaults)."""
        fields_set: frozenset[str] = self.__dict__["__fields_set__"]
        return fields_set

    def _values(self) -> Iterator[tuple[str, Any]]:
        for name in type(self).model_fields:
            yield name, self.__dict__[name]

    def model_dump(self, mode: Literal["python", "json"] = "python") -> dict[str, Any]:
        """The record as plain data: records as dicts, every field included; with
        ``mode="json"`` tuples become lists."""
        return {k: _dump(v, mode == "json") for k, v in self._values()}

    def model_copy(self, update: Mapping[str, Any] | None = None) -> Any:
        """A copy with the fields in ``update`` replaced (not validated: the caller's values)."""
        obj = object.__new__(type(self))
        obj.__dict__.update(self.__dict__)
        if update:
            obj.__dict__.update(update)
            obj.__dict__["__fields_set__"] = self.model_fields_set | set(update)
        return obj

    # -- value semantics --------------------------------------------------------------------

    def __setattr__(self, name: str, value: Any) -> None:
        raise AttributeError(f"{type(self).__name__} is frozen: cannot set {name!r}")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"{type(self).__name__} is frozen: cannot delete {name!r}")

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        assert isinstance(other, Record)
        return all(self.__dict__[k] == other.__dict__[k] for k in type(self).model_fields)

    def __hash__(self) -> int:
        return hash((type(self), tuple(v for _, v in self._values())))

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v!r}" for k, v in self._values())
        return f"{type(self).__name__}({inner})"


def _dump(v: Any, json_mode: bool) -> Any:
    if isinstance(v, Record):
        return v.model_dump("json" if json_mode else "python")
    if isinstance(v, tuple):
        items = [_dump(x, json_mode) for x in v]
        return items if json_mode else tuple(items)
    if isinstance(v, list):
        return [_dump(x, json_mode) for x in v]
    if isinstance(v, dict):
        return {k: _dump(x, json_mode) for k, x in v.items()}
    return v
