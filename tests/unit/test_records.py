"""covnet.records: the config layer's validated, frozen records.  Oracle values are the rules of
its module docstring; the round trip (dump, validate again) is a hypothesis property; every
shipped config keeps its hash (tests/golden holds the run directories' bits)."""

from __future__ import annotations

import copy
import math
import pickle
from pathlib import Path
from typing import Annotated, Any, Literal

import pytest
from hypothesis import given
from hypothesis import strategies as st

from covnet import kinds
from covnet.records import (
    MAX_MAGNITUDE,
    AfterValidator,
    Field,
    Placed,
    Record,
    ValidationError,
    field_validator,
    model_validator,
)

REPO = Path(__file__).resolve().parents[2]


def _positive(v: float) -> float:
    if not v > 0:
        raise ValueError("must be > 0")
    return v


def _even(v: int) -> int:
    if v % 2:
        raise ValueError(f"must be even, got {v}")
    return v


class Inner(Record):
    a: float
    b: int = 2


class Rec(Record):
    x: float = 1.0
    n: int = Field(default=3, ge=1, le=10)
    s: Annotated[str, Field(min_length=1, max_length=5, pattern=r"^[a-z]+$")] = "abc"
    flag: bool = False
    mode: Literal["one", "two", "three"] = "one"
    pair: Annotated[tuple[float, ...], Field(min_length=2, max_length=2)] = (0.0, 0.0)
    edge: tuple[str, str] | None = None
    table: dict[str, Inner] = Field(default_factory=dict)
    items: tuple[Inner, ...] = ()
    anything: Any = None
    even: Annotated[int, AfterValidator(_even)] = 0
    inner: Inner = Inner(a=1.0)


def problems(cls: type[Record], **data: Any) -> list[tuple[str, str, Any]]:
    with pytest.raises(ValidationError) as exc:
        cls.model_validate(data)
    return [(".".join(map(str, e["loc"])), e["type"], e["input"]) for e in exc.value.errors()]


# --- types are strict -----------------------------------------------------------------------


@pytest.mark.parametrize(
    "value", [True, "1.0", None, [1.0], math.inf, math.nan, 10**400, 1e308, -1e16, 10**16]
)
def test_a_float_field_takes_only_a_finite_number(value):
    [(loc, kind, given_)] = problems(Rec, x=value)
    assert loc == "x" and kind in ("float_type", "finite_number")


@pytest.mark.parametrize("value", [MAX_MAGNITUDE, -MAX_MAGNITUDE, 10**15, 1e-300])
def test_a_float_field_takes_magnitudes_up_to_the_limit(value):
    assert Rec(x=value).x == float(value)


def test_a_huge_value_is_named_by_check_and_run_not_a_traceback(tmp_path, capsys):
    """A sensor's standard deviation of 1e308 m passed the finite check and ended ``covnet
    run`` in an OverflowError; a desired covariance of 1e308 ended ``covnet check`` itself in
    numpy's LinAlgError (found by a fuzz of every number of the shipped configs)."""
    import yaml

    from covnet.cli.app import main

    for path, where in (
        (("sensors", 0, "sigma_x_m"), "sensors[0].sigma_x_m"),
        (("desired", 0, "diag", 1), "desired[0].diag[1]"),
    ):
        data = yaml.safe_load((REPO / "configs" / "paper.yaml").read_text())
        node = data
        for key in path[:-1]:
            node = node[key]
        node[path[-1]] = 1e308
        cfg = tmp_path / "huge.yaml"
        cfg.write_text(yaml.safe_dump(data))
        for cmd in (["check", str(cfg)], ["run", str(cfg), "--out", str(tmp_path / "o")]):
            assert main(cmd) == 2
            err = capsys.readouterr().err
            assert f"{where}: Input should be a number of magnitude at most 1e+15" in err
            assert "Traceback" not in err


def test_an_integer_becomes_a_float():
    r = Rec(x=3)
    assert r.x == 3.0 and type(r.x) is float


@pytest.mark.parametrize("value", [True, 2.0, "2"])
def test_an_int_field_takes_only_an_integer(value):
    assert problems(Rec, n=value) == [("n", "int_type", value)]


@pytest.mark.parametrize(
    "field,value,kind",
    [("s", 5, "string_type"), ("flag", 1, "bool_type"), ("flag", "yes", "bool_type")],
)
def test_strings_and_booleans_are_only_themselves(field, value, kind):
    assert problems(Rec, **{field: value}) == [(field, kind, value)]


def test_a_literal_takes_one_of_its_values_and_says_which():
    with pytest.raises(ValidationError) as exc:
        Rec(mode="four")
    assert exc.value.errors()[0]["msg"] == "Input should be 'one', 'two' or 'three'"


def test_a_list_becomes_a_tuple_and_a_string_is_not_a_tuple():
    assert Rec(pair=[1, 2.5]).pair == (1.0, 2.5)
    assert problems(Rec, pair="ab") == [("pair", "tuple_type", "ab")]


def test_a_fixed_tuple_names_the_missing_item_and_counts_an_extra_one():
    assert problems(Rec, edge=["a"]) == [("edge.1", "missing", ["a"])]
    assert problems(Rec, edge=["a", "b", "c"]) == [("edge", "too_long", ["a", "b", "c"])]
    assert Rec(edge=["a", "b"]).edge == ("a", "b")


def test_a_mapping_of_records_is_validated_entry_by_entry():
    r = Rec(table={"k": {"a": 1}})
    assert r.table == {"k": Inner(a=1.0)}
    assert problems(Rec, table={"k": {"a": "x"}, "j": 3}) == [
        ("table.k.a", "float_type", "x"),
        ("table.j", "model_type", 3),
    ]


def test_any_takes_anything_as_it_is():
    v = {"a": [1, 2]}
    assert Rec(anything=v).anything is v


# --- keys, constraints, checks ----------------------------------------------------------------


def test_every_problem_at_once_fields_in_order_then_unknown_keys():
    got = problems(Rec, zz=1, n=0, s="", inner={"b": 1})
    assert got == [
        ("n", "ge", 0),
        ("s", "too_short", ""),
        ("inner.a", "missing", {"b": 1}),
        ("zz", "extra_forbidden", 1),
    ]


@pytest.mark.parametrize(
    "data,msg",
    [
        ({"n": 11}, "Input should be less than or equal to 10"),
        ({"n": 0}, "Input should be greater than or equal to 1"),
        ({"s": "abcdef"}, "String should have at most 5 characters"),
        ({"s": "AB"}, "String should match pattern '^[a-z]+$'"),
        ({"pair": [1.0]}, "Tuple should have exactly 2 items after validation, not 1"),
    ],
)
def test_constraint_messages(data, msg):
    with pytest.raises(ValidationError) as exc:
        Rec.model_validate(data)
    [err] = exc.value.errors()
    assert err["msg"] == msg and err["input"] == next(iter(data.values()))


def test_a_bad_item_is_not_also_a_wrong_length():
    """YAML 1.1 reads 1.0e4 as text: the item is the cause, not the pair's length."""
    assert problems(Rec, pair=[1.0, "1.0e4"]) == [("pair.1", "float_type", "1.0e4")]
    assert problems(Rec, pair=["x"]) == [("pair.0", "float_type", "x")]


class Checked(Record):
    a: Annotated[int, AfterValidator(lambda v: v + 1)] = 0
    b: float = 1.0

    @field_validator("a")
    @classmethod
    def _double(cls, v: int) -> int:
        return 2 * v

    _b = field_validator("b")(_positive)

    @model_validator(mode="after")
    def _whole(self) -> Checked:
        if self.a == 8:
            raise ValueError("a whole-record problem")
        return self


def test_checks_run_in_order_after_the_type_and_a_record_check_last():
    assert Checked(a=1).a == 4  # (1 + 1) * 2: the type's check, then the field's
    assert problems(Checked, a=3) == [("", "value_error", {"a": 3})]
    with pytest.raises(ValidationError) as exc:
        Checked(b=-1.0, a="x")
    errs = exc.value.errors()
    assert [(e["loc"], e["type"]) for e in errs] == [(("a",), "int_type"), (("b",), "value_error")]
    assert errs[1]["msg"] == "must be > 0"


def _no_zero(v: tuple[int, ...]) -> tuple[int, ...]:
    if 0 in v:
        raise Placed((v.index(0), "n"), "must not be 0", "zero_item")
    return v


class Holder(Record):
    items: Annotated[tuple[int, ...], AfterValidator(_no_zero)] = ()


def test_a_placed_problem_is_reported_below_its_field_with_its_own_type():
    with pytest.raises(ValidationError) as exc:
        Holder(items=(3, 0))
    (err,) = exc.value.errors()
    assert (err["loc"], err["type"]) == (("items", 1, "n"), "zero_item")
    assert err["msg"] == "must not be 0"


def test_defaults_are_not_validated():
    class Loose(Record):
        n: int = Field(default=-5, ge=0)

    assert Loose().n == -5
    assert problems(Loose, n=-5) == [("n", "ge", -5)]


def test_a_subclass_has_its_bases_fields_first_and_their_checks():
    class Base(Record):
        p: float = 1.0
        _pos = field_validator("p")(_positive)

    class Child(Base):
        q: int = 0

    class Lenient(Base):
        _pos = field_validator("p")(lambda v: v)  # replaces the base's check of that name

    assert list(Child.model_fields) == ["p", "q"]
    assert problems(Child, p=-1.0, q=1) == [("p", "value_error", -1.0)]
    assert Child.model_fields["q"].annotation is int
    assert Lenient(p=-1.0).p == -1.0


def test_field_infos():
    f = Rec.model_fields
    assert f["n"].default == 3 and not f["n"].is_required()
    assert Inner.model_fields["a"].is_required()
    assert f["table"].get_default(call_default_factory=True) == {}
    assert f["mode"].annotation == Literal["one", "two", "three"]


# --- value semantics --------------------------------------------------------------------------


def test_records_are_frozen_values():
    r = Rec(x=2, items=[{"a": 1}])
    with pytest.raises(AttributeError):
        r.x = 3.0  # type: ignore[misc]
    assert r == Rec(x=2.0, items=({"a": 1.0},)) and r != Rec()
    assert hash(Inner(a=1.0)) == hash(Inner(a=1))
    for clone in (pickle.loads(pickle.dumps(r)), copy.deepcopy(r), copy.copy(r)):
        assert clone == r and clone.model_fields_set == r.model_fields_set


def test_dump_copy_and_the_fields_given():
    r = Rec(pair=[1, 2], items=[{"a": 1}])
    assert r.model_fields_set == {"pair", "items"}
    assert r.model_dump()["pair"] == (1.0, 2.0)
    js = r.model_dump(mode="json")
    assert js["pair"] == [1.0, 2.0] and js["items"] == [{"a": 1.0, "b": 2}]
    c = r.model_copy(update={"x": 5.0})
    assert c.x == 5.0 and r.x == 1.0 and c.model_fields_set == {"pair", "items", "x"}
    assert "Rec(x=1.0, n=3" in repr(r)


finite = st.floats(-MAX_MAGNITUDE, MAX_MAGNITUDE)  # what a float field takes
words = st.from_regex(r"[a-z]{1,5}", fullmatch=True)
inners = st.builds(lambda a, b: {"a": a, "b": b}, finite, st.integers())


@given(
    st.fixed_dictionaries(
        {},
        optional={
            "x": finite | st.integers(-(10**6), 10**6),
            "n": st.integers(1, 10),
            "s": words,
            "flag": st.booleans(),
            "mode": st.sampled_from(["one", "two", "three"]),
            "pair": st.lists(finite, min_size=2, max_size=2),
            "edge": st.none() | st.tuples(words, words),
            "table": st.dictionaries(words, inners, max_size=3),
            "items": st.lists(inners, max_size=3),
            "even": st.integers(-100, 100).map(lambda v: 2 * v),
        },
    )
)
def test_a_record_round_trips_through_its_json_dump(data):
    r = Rec.model_validate(data)
    again = Rec.model_validate(r.model_dump(mode="json"))
    assert again == r and again.model_dump(mode="json") == r.model_dump(mode="json")


@pytest.mark.parametrize("name", sorted(p.name for p in (REPO / "configs").glob("*.yaml")))
def test_every_shipped_config_round_trips(name):
    kind, cfg = kinds.load(REPO / "configs" / name)
    again = type(cfg).model_validate(cfg.model_dump(mode="json"))
    assert again == cfg
