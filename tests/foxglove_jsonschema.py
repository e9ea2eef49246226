"""What Foxglove accepts of a ``jsonschema`` channel, and of its JSON messages.

Foxglove (and Lichtblick, its open-source fork) turns a channel's JSON Schema into message
definitions before it shows a single message: ``parseJsonSchema`` of their ``mcap-support``
package.  A schema it cannot parse makes it reject the whole channel (no plot, no raw view), in
a recording and live alike, although every message validates with ``jsonschema``.  The rules
below are that parser's, written out (conservatively where the two apps differ):

* the root, and every nested object, has ``"type": "object"`` and a ``properties`` mapping;
* each property's ``type`` is ONE string among ``boolean``, ``string``, ``number``, ``integer``,
  ``object``, ``array``: never ``null``, never a list of types (``["number", "null"]`` is
  rejected: "Unsupported type"), never absent;
* no ``oneOf`` / ``anyOf`` / ``allOf`` / ``$ref`` (Foxglove reads ``oneOf`` only as a list of
  numeric constants, Lichtblick not at all, and neither resolves references);
* a string has no ``contentEncoding`` but ``base64``;
* an array's ``items`` is one schema whose type is ``boolean``, ``string`` (without
  ``contentEncoding``), ``number``, ``integer`` or ``object`` (checked the same way): no arrays
  of arrays.

And a message is ``JSON.parse``-able (no ``NaN`` / ``Infinity``) with no ``null`` anywhere: a
value that is not known is left out.
"""

from __future__ import annotations

import json
from typing import Any

SCALARS = ("boolean", "string", "number", "integer")
TYPES = (*SCALARS, "object", "array")
COMBINATORS = ("oneOf", "anyOf", "allOf", "$ref")


def schema_problems(schema: Any, where: str = "") -> list[str]:
    """Why Foxglove's JSON-schema parser would reject ``schema`` (an object schema), one line
    per problem naming the field's path; empty if it would accept it."""
    where = where or "<root>"
    if not isinstance(schema, dict):
        return [f"{where}: expected a schema object, got {schema!r}"]
    if schema.get("type") != "object":
        return [f'{where}: expected "type": "object", got {schema.get("type")!r}']
    props = schema.get("properties")
    if not isinstance(props, dict):
        return [f"{where}: an object schema needs a 'properties' mapping, got {props!r}"]
    problems = []
    for name, field in props.items():
        path = name if where == "<root>" else f"{where}.{name}"
        problems += _field_problems(field, path, in_array=False)
    return problems


def _field_problems(field: Any, path: str, *, in_array: bool) -> list[str]:
    what = f"{path}[]" if in_array else path
    if not isinstance(field, dict):
        return [f"{what}: expected a schema object, got {field!r}"]
    found = [k for k in COMBINATORS if k in field]
    if found:
        return [f"{what}: {', '.join(found)} is not supported"]
    t = field.get("type")
    if not isinstance(t, str):
        return [f"{what}: type must be one string, got {t!r}"]
    allowed = (*SCALARS, "object") if in_array else TYPES
    if t not in allowed:
        return [f"{what}: unsupported type {t!r} (one of {', '.join(allowed)})"]
    if t == "string" and "contentEncoding" in field:
        if in_array or field["contentEncoding"] != "base64":
            return [f"{what}: unsupported contentEncoding {field['contentEncoding']!r}"]
    if t == "object":
        return schema_problems(field, what)
    if t == "array":
        return _field_problems(field.get("items"), path, in_array=True)
    return []


def _no_constant(text: str) -> Any:
    raise ValueError(f"{text} is not JSON (JSON.parse rejects it)")


def message_problems(data: bytes | str) -> list[str]:
    """Why a JSON message is not what Foxglove plots: not strict JSON, or a ``null`` in it
    (paths of the nulls)."""
    try:
        doc = json.loads(data, parse_constant=_no_constant)
    except ValueError as exc:
        return [str(exc)]
    problems: list[str] = []

    def walk(v: Any, path: str) -> None:
        if v is None:
            problems.append(f"{path or '<root>'}: null")
        elif isinstance(v, dict):
            for k, x in v.items():
                walk(x, f"{path}.{k}" if path else k)
        elif isinstance(v, list):
            for i, x in enumerate(v):
                walk(x, f"{path}[{i}]")

    walk(doc, "")
    return problems
