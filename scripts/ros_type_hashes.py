#!/usr/bin/env python3
"""Compute ROS 2 (Jazzy) RIHS01 interface type hashes (REP 2011) from .msg/.srv/.action files.

The hash is the one rmw_zenoh puts into its key expressions, e.g.
``RIHS01_df668c74...`` for ``std_msgs/msg/String``.

How the hash is formed (mirrors what rosidl_generator_type_description does):

* every interface becomes an "individual type description"
  ``{"type_name": "pkg/msg/Name", "fields": [field, ...]}`` where a field is
  ``{"name": ..., "type": {"type_id": ..., "capacity": ...,
  "string_capacity": ..., "nested_type_name": ...}}`` (default values are not
  part of the hashed text; constants are not fields at all);
* the full description is ``{"type_description": <the type>,
  "referenced_type_descriptions": [<every transitively referenced type,
  sorted by type_name>]}``;
* the hash is sha256 over that JSON serialized with ``", "`` / ``": "``
  separators, no indentation, keys in the order given above, ASCII only.

A service ``pkg/srv/Name`` is described as a type with three nested fields
``request_message``, ``response_message`` and ``event_message``; the event
message ``Name_Event`` has ``info`` (service_msgs/msg/ServiceEventInfo) and
``request``/``response`` as sequences bounded to 1 element.  Actions are
expanded the same way rosidl does (goal, result, feedback, the SendGoal and
GetResult services and the FeedbackMessage).

Usage::

    ros_type_hashes.py [-I DEP_PKG_DIR ...] PKG_DIR [PKG_DIR ...]

Each PKG_DIR is a package source folder (its name is the package name) with
msg/*.msg, srv/*.srv and/or action/*.action.  Types of the PKG_DIRs are
printed as ``type_name<TAB>RIHS01_<hex>`` lines, sorted; -I folders are only
used to resolve referenced types (e.g. service_msgs and builtin_interfaces,
needed by every service).

Python 3.11 standard library only.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

# --- field type ids (type_description_interfaces/msg/FieldType.msg) -------------------------

NESTED = 1
# .msg primitive name -> base type id.  'char' is an alias of uint8 and 'byte' of octet in
# the .msg -> .idl conversion.
PRIMITIVE_IDS = {
    'int8': 2,
    'uint8': 3,
    'char': 3,
    'int16': 4,
    'uint16': 5,
    'int32': 6,
    'uint32': 7,
    'int64': 8,
    'uint64': 9,
    'float32': 10,
    'float64': 11,
    'bool': 15,
    'byte': 16,
    'string': 17,
    'wstring': 18,
}
BOUNDED_STRING = 21
BOUNDED_WSTRING = 22
# Offsets added to the element's id for containers.
ARRAY_OFFSET = 48
BOUNDED_SEQUENCE_OFFSET = 96
UNBOUNDED_SEQUENCE_OFFSET = 144

EMPTY_STRUCT_MEMBER = 'structure_needs_at_least_one_member'
RIHS01_PREFIX = 'RIHS01_'


@dataclass
class FieldType:
    type_id: int
    capacity: int = 0
    string_capacity: int = 0
    nested_type_name: str = ''

    def as_dict(self) -> dict:
        return {
            'type_id': self.type_id,
            'capacity': self.capacity,
            'string_capacity': self.string_capacity,
            'nested_type_name': self.nested_type_name,
        }


@dataclass
class TypeDesc:
    type_name: str
    fields: list[tuple[str, FieldType]] = field(default_factory=list)

    def as_dict(self) -> dict:
        return {
            'type_name': self.type_name,
            'fields': [{'name': n, 'type': t.as_dict()} for n, t in self.fields],
        }


def nested(type_name: str) -> FieldType:
    return FieldType(NESTED, nested_type_name=type_name)


# --- .msg parsing ---------------------------------------------------------------------------

_TYPE_RE = re.compile(r'^(?P<base>[^\[\]]+)(?:\[(?P<arr>[^\]]*)\])?$')


class ParseError(Exception):
    pass


def parse_field_type(type_string: str, pkg: str, local_msgs: set[str]) -> FieldType:
    m = _TYPE_RE.match(type_string)
    if not m:
        raise ParseError(f'bad type {type_string!r}')
    base, arr = m.group('base'), m.group('arr')

    string_capacity = 0
    nested_name = ''
    if base.startswith('string<=') or base.startswith('wstring<='):
        kind, bound = base.split('<=', 1)
        string_capacity = int(bound)
        base_id = BOUNDED_STRING if kind == 'string' else BOUNDED_WSTRING
    elif base in PRIMITIVE_IDS:
        base_id = PRIMITIVE_IDS[base]
    else:
        parts = base.split('/')
        if len(parts) == 2:
            ref_pkg, name = parts
        elif len(parts) == 3 and parts[1] == 'msg':
            ref_pkg, name = parts[0], parts[2]
        elif len(parts) == 1:
            name = parts[0]
            # ROS 1 style bare 'Header' means std_msgs/Header unless the package has its own.
            ref_pkg = 'std_msgs' if name == 'Header' and name not in local_msgs else pkg
        else:
            raise ParseError(f'bad type {type_string!r}')
        base_id = NESTED
        nested_name = f'{ref_pkg}/msg/{name}'

    capacity = 0
    type_id = base_id
    if arr is not None:
        if arr == '':
            type_id += UNBOUNDED_SEQUENCE_OFFSET
        elif arr.startswith('<='):
            type_id += BOUNDED_SEQUENCE_OFFSET
            capacity = int(arr[2:])
        else:
            type_id += ARRAY_OFFSET
            capacity = int(arr)
    return FieldType(type_id, capacity, string_capacity, nested_name)


def parse_msg_text(text: str, pkg: str, type_name: str, local_msgs: set[str]) -> TypeDesc:
    desc = TypeDesc(type_name)
    for raw in text.replace('\t', ' ').splitlines():
        line = raw
        hash_at = line.find('#')  # rosidl also cuts at the first '#'
        if hash_at >= 0:
            line = line[:hash_at]
        line = line.strip()
        if not line:
            continue
        type_string, _, rest = line.partition(' ')
        rest = rest.lstrip()
        if not rest:
            raise ParseError(f'{type_name}: bad line {raw!r}')
        if '=' in rest:
            continue  # constant
        name = rest.partition(' ')[0]  # anything after is a default value (not hashed)
        try:
            desc.fields.append((name, parse_field_type(type_string, pkg, local_msgs)))
        except (ParseError, ValueError) as e:
            raise ParseError(f'{type_name}: {e}') from None
    if not desc.fields:
        desc.fields.append((EMPTY_STRUCT_MEMBER, FieldType(PRIMITIVE_IDS['uint8'])))
    return desc


def split_sections(text: str, count: int, what: str) -> list[str]:
    lines = text.splitlines()
    seps = [i for i, line in enumerate(lines) if line == '---']
    if len(seps) != count - 1:
        raise ParseError(f'{what}: expected {count - 1} "---" separator(s)')
    bounds = [-1] + seps + [len(lines)]
    return ['\n'.join(lines[a + 1:b]) for a, b in zip(bounds, bounds[1:])]


def service_types(pkg: str, kind: str, name: str, req: TypeDesc, resp: TypeDesc) -> list[TypeDesc]:
    base = f'{pkg}/{kind}/{name}'
    event = TypeDesc(f'{base}_Event', [
        ('info', nested('service_msgs/msg/ServiceEventInfo')),
        ('request', FieldType(NESTED + BOUNDED_SEQUENCE_OFFSET, 1, 0, req.type_name)),
        ('response', FieldType(NESTED + BOUNDED_SEQUENCE_OFFSET, 1, 0, resp.type_name)),
    ])
    srv = TypeDesc(base, [
        ('request_message', nested(req.type_name)),
        ('response_message', nested(resp.type_name)),
        ('event_message', nested(event.type_name)),
    ])
    return [srv, req, resp, event]


def load_package(pkg_dir: Path) -> dict[str, TypeDesc]:
    pkg = pkg_dir.name
    types: dict[str, TypeDesc] = {}
    msg_files = sorted((pkg_dir / 'msg').glob('*.msg'))
    local_msgs = {p.stem for p in msg_files}

    def read(p: Path) -> str:
        return p.read_text(encoding='utf-8')

    for p in msg_files:
        d = parse_msg_text(read(p), pkg, f'{pkg}/msg/{p.stem}', local_msgs)
        types[d.type_name] = d

    for p in sorted((pkg_dir / 'srv').glob('*.srv')):
        base = f'{pkg}/srv/{p.stem}'
        req_t, resp_t = split_sections(read(p), 2, base)
        req = parse_msg_text(req_t, pkg, f'{base}_Request', local_msgs)
        resp = parse_msg_text(resp_t, pkg, f'{base}_Response', local_msgs)
        for d in service_types(pkg, 'srv', p.stem, req, resp):
            types[d.type_name] = d

    for p in sorted((pkg_dir / 'action').glob('*.action')):
        name = p.stem
        base = f'{pkg}/action/{name}'
        goal_t, result_t, feedback_t = split_sections(read(p), 3, base)
        goal = parse_msg_text(goal_t, pkg, f'{base}_Goal', local_msgs)
        result = parse_msg_text(result_t, pkg, f'{base}_Result', local_msgs)
        feedback = parse_msg_text(feedback_t, pkg, f'{base}_Feedback', local_msgs)
        uuid = nested('unique_identifier_msgs/msg/UUID')
        send_goal = service_types(
            pkg, 'action', f'{name}_SendGoal',
            TypeDesc(f'{base}_SendGoal_Request',
                     [('goal_id', uuid), ('goal', nested(goal.type_name))]),
            TypeDesc(f'{base}_SendGoal_Response',
                     [('accepted', FieldType(PRIMITIVE_IDS['bool'])),
                      ('stamp', nested('builtin_interfaces/msg/Time'))]))
        get_result = service_types(
            pkg, 'action', f'{name}_GetResult',
            TypeDesc(f'{base}_GetResult_Request', [('goal_id', uuid)]),
            TypeDesc(f'{base}_GetResult_Response',
                     [('status', FieldType(PRIMITIVE_IDS['int8'])),
                      ('result', nested(result.type_name))]))
        feedback_msg = TypeDesc(f'{base}_FeedbackMessage',
                                [('goal_id', uuid), ('feedback', nested(feedback.type_name))])
        action = TypeDesc(base, [
            ('goal', nested(goal.type_name)),
            ('result', nested(result.type_name)),
            ('feedback', nested(feedback.type_name)),
            ('send_goal_service', nested(send_goal[0].type_name)),
            ('get_result_service', nested(get_result[0].type_name)),
            ('feedback_message', nested(feedback_msg.type_name)),
        ])
        for d in [action, goal, result, feedback, *send_goal, *get_result, feedback_msg]:
            types[d.type_name] = d
    return types


# --- hashing --------------------------------------------------------------------------------

def full_description(type_name: str, all_types: dict[str, TypeDesc]) -> dict:
    seen: set[str] = set()
    stack = [type_name]
    while stack:
        cur = stack.pop()
        try:
            desc = all_types[cur]
        except KeyError:
            raise SystemExit(f'error: type {cur!r} (needed by {type_name}) not found; '
                             'pass its package folder with -I') from None
        for _, ft in desc.fields:
            ref = ft.nested_type_name
            if ref and ref not in seen:
                seen.add(ref)
                stack.append(ref)
    seen.discard(type_name)  # cannot happen for valid ROS types, but be safe
    return {
        'type_description': all_types[type_name].as_dict(),
        'referenced_type_descriptions': [all_types[n].as_dict() for n in sorted(seen)],
    }


def rihs01(type_name: str, all_types: dict[str, TypeDesc]) -> str:
    text = json.dumps(full_description(type_name, all_types), ensure_ascii=True,
                      indent=None, separators=(', ', ': '), sort_keys=False)
    return RIHS01_PREFIX + hashlib.sha256(text.encode('utf-8')).hexdigest()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split('\n\n')[0])
    ap.add_argument('packages', nargs='+', type=Path, help='package folders to hash')
    ap.add_argument('-I', '--include', action='append', default=[], type=Path,
                    help='package folder only used to resolve referenced types')
    ap.add_argument('--dump', metavar='TYPE',
                    help='print the hashed JSON text of one type instead of the table')
    args = ap.parse_args(argv)

    all_types: dict[str, TypeDesc] = {}
    wanted: list[str] = []
    for d in args.include:
        all_types.update(load_package(d))
    for d in args.packages:
        types = load_package(d)
        if not types:
            print(f'warning: no interfaces found in {d}', file=sys.stderr)
        all_types.update(types)
        wanted.extend(types)

    if args.dump:
        print(json.dumps(full_description(args.dump, all_types), separators=(', ', ': ')))
        return 0
    for name in sorted(set(wanted)):
        print(f'{name}\t{rihs01(name, all_types)}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
