"""The URScript subset labcal emits: a static checker of the controller's rules, and an interpreter for tests.

``check(script)`` enforces, on the text alone, the rules a UR controller applies that labcal's scripts must keep:

- statements: ``def``/``end``, ``while``, ``if``/``elif``/``else``, ``local``/plain/indexed assignment, ``return``,
  ``halt``, calls; expressions: names, numbers, strings, + - * /, comparisons, and/or/not, parentheses, list
  literals and indexing. Python-only syntax (slices, comprehensions, ``**``, ``%``, attributes) is refused;
- **list capacity** (PolyScope ≥ 5.15: a list is assigned only to an existing list of greater or equal capacity;
  a literal's capacity is its length): every whole-list assignment to an existing variable must provably fit,
  so a one-element placeholder later given a longer list is an error;
- **integer indexing**: every index is an int expression (int literals and int variables under + - *);
- **types stay fixed**: a variable keeps the type of its first assignment (an int counter never takes a float);
- **scope**: inside a function every assigned variable is a parameter or declared ``local`` (URScript would
  otherwise write a program variable of the same name);
- **built-ins**: only those in :data:`BUILTINS`; every other call is to a function the script defines, with the
  right number of arguments.

``load(script, float32=False)`` translates the script line by line into Python and runs its top level; it counts
every statement it executes (each simple statement and each if/elif/while test) and the statements between two
``sync()`` calls (``stats``), and in ``float32=True`` mode computes like the controller: every float literal and
every built-in result is a 32-bit float, and numpy keeps float32 arithmetic in float32.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field

import numpy as np

_NAME = r"[A-Za-z_][A-Za-z0-9_]*"
_STATEMENTS = [
    ("def", re.compile(rf"^def (?P<name>{_NAME})\((?P<params>({_NAME}(, {_NAME})*)?)\):$")),
    ("end", re.compile(r"^end$")),
    ("cond", re.compile(r"^(?P<kw>while|if|elif) (?P<e>.+):$")),
    ("else", re.compile(r"^else:$")),
    ("assign", re.compile(rf"^(?P<local>local )?(?P<name>{_NAME}) = (?P<e>.+)$")),
    ("setitem", re.compile(rf"^(?P<name>{_NAME})\[(?P<i>[^\]]+)\] = (?P<e>.+)$")),
    ("return", re.compile(r"^return (?P<e>.+)$")),
    ("halt", re.compile(r"^halt$")),
    ("call", re.compile(rf"^(?P<e>{_NAME}\(.*\))$")),
]
_TOKEN = re.compile(
    r'\s*(?:(?P<num>\d+\.\d*(?:e[-+]?\d+)?|\d+(?:e[-+]?\d+)?)|(?P<name>[A-Za-z_]\w*)|(?P<op><=|>=|==|!=|[-+*/<>()\[\],=])|(?P<str>"[^"]*"))'
)
_KEYWORDS = {"and", "or", "not", "True", "False"}
FLOAT_FUNCTIONS = {"sin", "cos", "sqrt", "atan2", "pow"}
BUILTINS = {
    "sin": 1,
    "cos": 1,
    "sqrt": 1,
    "atan2": 2,
    "pow": 2,
    "sync": 0,
    "popup": 1,
    "textmsg": None,
    "str_cat": 2,
    "movej": 1,
}
KEYWORDS = {"popup": {"title", "warning", "error", "blocking"}, "movej": {"a", "v", "t", "r"}}
ALLOWED_CALLS = set(BUILTINS)


class Halted(Exception):
    """The script executed ``halt`` (after a popup)."""


class URScriptRuleError(SyntaxError):
    """The script breaks a rule of the URScript subset or of the controller (the message names line and rule)."""


# ------------------------------------------------------------------------------------------------------------
# Tokens and expressions


def _tokens(expr: str, where: str) -> list[tuple[str, str]]:
    out, pos = [], 0
    while pos < len(expr):
        if expr[pos:].strip() == "":
            break
        m = _TOKEN.match(expr, pos)
        if not m or m.end() == pos:
            raise URScriptRuleError(f"{where}: not in the URScript subset: {expr[pos:]!r}")
        kind = m.lastgroup
        out.append((kind, m.group(kind)))
        pos = m.end()
    code = re.sub(r'"[^"]*"', '""', expr)  # strings (popup texts) may hold any character
    if "**" in code or "//" in code or "%" in code or " for " in f" {code} " or ":" in code:
        raise URScriptRuleError(f"{where}: Python-only syntax in {expr!r}")
    return out


INT, FLOAT, BOOL, STR, ANY, NONE = "int", "float", "bool", "str", "any", "none"


@dataclass(frozen=True)
class ListT:
    length: int | None  # None: not known statically (a parameter's list)
    elem: str


class _Expr:
    """Recursive-descent typing of one expression: returns its type, raising URScriptRuleError on a broken rule."""

    def __init__(self, tokens, where: str, lookup, call_type) -> None:
        self.t, self.i, self.where, self.lookup, self.call_type = tokens, 0, where, lookup, call_type

    def fail(self, msg: str):
        raise URScriptRuleError(f"{self.where}: {msg}")

    def peek(self):
        return self.t[self.i] if self.i < len(self.t) else (None, None)

    def take(self, value=None):
        tok = self.peek()
        if tok[0] is None or (value is not None and tok[1] != value):
            self.fail(f"expected {value!r}, got {tok[1]!r}")
        self.i += 1
        return tok

    def parse(self):
        ty = self.or_()
        if self.i != len(self.t):
            self.fail(f"unexpected {self.t[self.i][1]!r}")
        return ty

    def or_(self):
        ty = self.and_()
        while self.peek()[1] == "or":
            self.take()
            self.and_()
            ty = BOOL
        return ty

    def and_(self):
        ty = self.not_()
        while self.peek()[1] == "and":
            self.take()
            self.not_()
            ty = BOOL
        return ty

    def not_(self):
        if self.peek()[1] == "not":
            self.take()
            self.not_()
            return BOOL
        return self.cmp()

    def cmp(self):
        ty = self.arith()
        if self.peek()[1] in ("<", ">", "<=", ">=", "==", "!="):
            self.take()
            self.arith()
            return BOOL
        return ty

    def _combine(self, a, b, op):
        if isinstance(a, ListT) or isinstance(b, ListT):
            self.fail(f"arithmetic on a list ({op})")
        if a == INT and b == INT:
            if op == "/":
                self.fail("'/' of two ints: write a float literal (URScript integer division differs)")
            return INT
        return FLOAT

    def arith(self):
        ty = self.term()
        while self.peek()[1] in ("+", "-"):
            op = self.take()[1]
            ty = self._combine(ty, self.term(), op)
        return ty

    def term(self):
        ty = self.unary()
        while self.peek()[1] in ("*", "/"):
            op = self.take()[1]
            ty = self._combine(ty, self.unary(), op)
        return ty

    def unary(self):
        if self.peek()[1] == "-":
            self.take()
            return self.unary()
        return self.postfix()

    def postfix(self):
        ty = self.atom()
        while self.peek()[1] == "[":
            self.take("[")
            index = self.or_()
            self.take("]")
            if index not in (INT,):
                self.fail(f"list index must be an int expression, got {index}")
            if isinstance(ty, ListT):
                ty = ty.elem
            elif ty == ANY:
                ty = ANY
            else:
                self.fail(f"indexing a {ty}")
        return ty

    def atom(self):
        kind, value = self.take()
        if kind == "num":
            return FLOAT if ("." in value or "e" in value) else INT
        if kind == "str":
            return STR
        if value == "(":
            ty = self.or_()
            self.take(")")
            return ty
        if value == "[":
            elems = []
            if self.peek()[1] != "]":
                elems.append(self.or_())
                while self.peek()[1] == ",":
                    self.take()
                    elems.append(self.or_())
            self.take("]")
            concrete = {e for e in elems if e != ANY}
            if len(concrete) > 1:
                self.fail(f"a list holds one type, this literal mixes {sorted(map(str, concrete))}")
            elem = concrete.pop() if concrete else FLOAT
            if isinstance(elem, ListT):
                self.fail("nested lists")
            return ListT(len(elems), elem)
        if kind != "name":
            self.fail(f"unexpected {value!r}")
        if value in ("True", "False"):
            return BOOL
        if value in _KEYWORDS:
            self.fail(f"unexpected {value!r}")
        if self.peek()[1] == "(":
            self.take("(")
            args, keywords = 0, []
            if self.peek()[1] != ")":
                while True:
                    if self.peek()[0] == "name" and self.i + 1 < len(self.t) and self.t[self.i + 1][1] == "=":
                        keywords.append(self.take()[1])
                        self.take("=")
                    else:
                        args += 1
                    self.or_()
                    if self.peek()[1] != ",":
                        break
                    self.take(",")
            self.take(")")
            return self.call_type(value, args, keywords, self.where)
        return self.lookup(value, self.where)


# ------------------------------------------------------------------------------------------------------------
# Static checker


@dataclass
class _Function:
    name: str
    params: tuple[str, ...]
    body: list  # (line number, indent, kind, match)
    ret: object = None
    state: str = "new"  # new | checking | done


@dataclass
class _Scope:
    vars: dict = field(default_factory=dict)
    params: frozenset = frozenset()
    function: bool = False


def _parse(script: str) -> list:
    """(line number, indent, kind, match) of every statement, comments and blank lines dropped."""
    out = []
    for number, raw in enumerate(script.splitlines(), start=1):
        line = raw.split("#", 1)[0].rstrip() if '"' not in raw else raw.rstrip()
        body = line.strip()
        if not body:
            continue
        found = next(((kind, pattern.match(body)) for kind, pattern in _STATEMENTS if pattern.match(body)), None)
        if found is None:
            raise URScriptRuleError(f"line {number}: statement not in the URScript subset: {body!r}")
        out.append((number, len(line) - len(line.lstrip()), *found))
    return out


def _blocks(stmts: list) -> list:
    """Nest statements: a def's body is its statements up to the matching ``end`` (by block depth)."""
    out, i = [], 0
    while i < len(stmts):
        number, indent, kind, m = stmts[i]
        if kind != "def":
            out.append(stmts[i])
            i += 1
            continue
        depth, j = 1, i + 1
        while j < len(stmts) and depth:
            k = stmts[j][2]
            if k in ("def",) or (k == "cond" and stmts[j][3].group("kw") in ("while", "if")):
                depth += 1
            elif k == "end":
                depth -= 1
            j += 1
        if depth:
            raise URScriptRuleError(f"line {number}: def {m.group('name')} has no end")
        out.append((number, indent, "def", m, stmts[i + 1 : j - 1]))
        i = j
    return out


class _Checker:
    def __init__(self) -> None:
        self.functions: dict[str, _Function] = {}
        self.globals = _Scope()

    def check_container(self, stmts: list, scope: _Scope) -> None:
        nested = _blocks(stmts)
        for item in nested:
            if item[2] == "def":
                m = item[3]
                params = tuple(p for p in m.group("params").split(", ") if p)
                if m.group("name") in self.functions or m.group("name") in BUILTINS:
                    raise URScriptRuleError(f"line {item[0]}: function {m.group('name')} defined twice or a builtin")
                self.functions[m.group("name")] = _Function(m.group("name"), params, item[4])
        for item in nested:
            if item[2] == "def":
                continue
            if item[2] == "return":
                raise URScriptRuleError(f"line {item[0]}: return outside a function")
            self.statement(item, scope, None)
        for fn in self.functions.values():
            self.analyse(fn)

    def analyse(self, fn: _Function) -> None:
        if fn.state == "done":
            return
        if fn.state == "checking":  # recursion: its return type is whatever the other returns say
            return
        fn.state = "checking"
        scope = _Scope({p: ANY for p in fn.params}, frozenset(fn.params), True)
        for item in _blocks(fn.body):
            if item[2] == "def":
                raise URScriptRuleError(f"line {item[0]}: a def inside a function")
            self.statement(item, scope, fn)
        fn.state = "done"

    def lookup(self, scope: _Scope):
        def find(name, where):
            if name in scope.vars:
                return scope.vars[name]
            if name in self.globals.vars:
                return self.globals.vars[name]
            raise URScriptRuleError(f"{where}: {name!r} is used before it is assigned")

        return find

    def call_type(self, name, args, keywords, where):
        if name in BUILTINS:
            want = BUILTINS[name]
            if want is not None and args != want:
                raise URScriptRuleError(f"{where}: {name}() takes {want} argument(s), got {args}")
            if not set(keywords) <= KEYWORDS.get(name, set()):
                raise URScriptRuleError(f"{where}: {name}() has no keyword(s) {sorted(set(keywords))}")
            return FLOAT if name in FLOAT_FUNCTIONS else (STR if name == "str_cat" else NONE)
        fn = self.functions.get(name)
        if fn is None:
            raise URScriptRuleError(f"{where}: {name}() is neither a URScript built-in we allow nor defined here")
        if args != len(fn.params) or keywords:
            raise URScriptRuleError(f"{where}: {name}() takes {len(fn.params)} argument(s), got {args}")
        self.analyse(fn)
        return fn.ret if fn.ret is not None else ANY

    def expr(self, text: str, scope: _Scope, where: str):
        return _Expr(_tokens(text, where), where, self.lookup(scope), self.call_type).parse()

    def assign(self, name, ty, declared, scope: _Scope, where: str, local: bool) -> None:
        if ty in (NONE, STR):
            raise URScriptRuleError(f"{where}: assigning a {ty} to {name!r}")
        if local or name not in declared:
            if scope.function and not local and name not in scope.params:
                raise URScriptRuleError(
                    f"{where}: {name!r} is assigned in a function without 'local' (it would write a program variable)"
                )
            if local and name in scope.vars and name not in scope.params:
                raise URScriptRuleError(f"{where}: {name!r} is declared local twice")
            if isinstance(ty, ListT) and ty.length is None:
                raise URScriptRuleError(f"{where}: {name!r} is created from a list of unknown size")
            scope.vars[name] = ty
            return
        old = declared[name]
        if old == ANY:
            if isinstance(ty, ListT):
                raise URScriptRuleError(f"{where}: cannot prove parameter {name!r} has room for a {ty.length}-list")
            return
        if isinstance(old, ListT) or isinstance(ty, ListT):
            if not (isinstance(old, ListT) and isinstance(ty, ListT)):
                other = ty if isinstance(old, ListT) else old
                raise URScriptRuleError(f"{where}: {name!r} changes between a list and a {other}")
            if ty.length is None or ty.length > old.length:
                raise URScriptRuleError(
                    f"{where}: list capacity: a {ty.length}-element list is assigned to {name!r}, created with "
                    f"capacity {old.length} (PolyScope >= 5.15 refuses it; create the list at its full size)"
                )
            if ty.elem not in (old.elem, ANY):
                raise URScriptRuleError(f"{where}: {name!r} is a list of {old.elem}, assigned a list of {ty.elem}")
            return
        if ty != ANY and ty != old:
            raise URScriptRuleError(f"{where}: {name!r} was created as {old} and is assigned a {ty}")

    def statement(self, item, scope: _Scope, fn: _Function | None) -> None:
        number, _indent, kind, m = item[:4]
        where = f"line {number}"
        if kind in ("end", "else", "halt"):
            return
        if kind == "cond":
            ty = self.expr(m.group("e"), scope, where)
            if ty not in (BOOL, ANY):
                raise URScriptRuleError(f"{where}: {m.group('kw')} needs a boolean, got {ty}")
            return
        if kind == "call":
            self.expr(m.group("e"), scope, where)
            return
        if kind == "return":
            ty = self.expr(m.group("e"), scope, where)
            if isinstance(fn.ret, ListT) and isinstance(ty, ListT):
                if ty.length is None or fn.ret.length is None:
                    fn.ret = ListT(None, ty.elem)
                else:
                    fn.ret = ListT(max(ty.length, fn.ret.length), ty.elem)
            elif fn.ret is None or fn.ret == ANY:
                fn.ret = ty
            elif ty not in (fn.ret, ANY):
                raise URScriptRuleError(f"{where}: {fn.name} returns a {fn.ret} and a {ty}")
            return
        if kind == "assign":
            ty = self.expr(m.group("e"), scope, where)
            declared = scope.vars if scope.function else {**self.globals.vars, **scope.vars}
            target = scope if (scope.function or scope is not self.globals) else self.globals
            self.assign(m.group("name"), ty, declared, target, where, bool(m.group("local")))
            return
        if kind == "setitem":
            name = m.group("name")
            base = self.lookup(scope)(name, where)
            index = self.expr(m.group("i"), scope, where)
            if index != INT:
                raise URScriptRuleError(f"{where}: list index must be an int expression, got {index}")
            ty = self.expr(m.group("e"), scope, where)
            if scope.function and name not in scope.vars:
                raise URScriptRuleError(f"{where}: a function writes into the program list {name!r}")
            if isinstance(base, ListT):
                if ty not in (base.elem, ANY) and not (base.elem == FLOAT and ty == INT):
                    raise URScriptRuleError(f"{where}: {name!r} holds {base.elem}, assigned a {ty}")
            elif base != ANY:
                raise URScriptRuleError(f"{where}: {name!r} is not a list")
            return
        raise URScriptRuleError(f"{where}: unexpected {kind}")


def check(script: str) -> None:
    """Raise URScriptRuleError (a SyntaxError) naming the line and rule the script breaks; None when it is clean.

    A script that is one ``def program(): … end`` is checked as a program: its top-level statements are the
    program's variables (URScript's global scope) and its nested defs are the functions.
    """
    stmts = _parse(script)
    checker = _Checker()
    top = _blocks(stmts)
    if len(top) == 1 and top[0][2] == "def" and not top[0][3].group("params"):
        checker.check_container(top[0][4], checker.globals)
    else:
        checker.check_container(stmts, checker.globals)


# ------------------------------------------------------------------------------------------------------------
# Interpreter


@dataclass
class Stats:
    """Statements executed: in total, since the last sync(), the most between two syncs, and the syncs."""

    total: int = 0
    window: int = 0
    max_window: int = 0
    max_window_end: int = 0  # script line number where the longest stretch without sync() ended
    syncs: int = 0
    messages: list = field(default_factory=list)

    def step(self, line: int = 0) -> bool:
        self.total += 1
        self.window += 1
        if self.window > self.max_window:
            self.max_window = self.window
            self.max_window_end = line
        return True

    def sync(self) -> None:
        self.syncs += 1
        self.window = 0

    def reset(self) -> None:
        self.total = self.window = self.max_window = self.syncs = 0


def _float32_literals(expr: str) -> str:
    out, pos = [], 0
    for m in _TOKEN.finditer(expr):
        if m.start() != pos:
            break
        text = m.group(0)
        num = m.group("num")
        if num is not None and ("." in num or "e" in num):
            text = text.replace(num, f"_F({num})")
        out.append(text)
        pos = m.end()
    return "".join(out) + expr[pos:]


def translate(script: str, float32: bool = False) -> str:
    """Python source of the script (the checker's statement forms only), counting statements through ``_S()``."""
    out = []
    fix = _float32_literals if float32 else (lambda e: e)
    for number, indent, kind, m in _parse(script):
        pad = " " * indent
        where = f"line {number}"
        for group in ("e", "i"):
            if group in m.re.groupindex and m.group(group) is not None:
                _tokens(m.group(group), where)
        if kind == "end":
            continue
        if kind == "def":
            out.append(f"{pad}def {m.group('name')}({m.group('params')}):")
        elif kind == "cond":
            out.append(f"{pad}{m.group('kw')} _S({number}) and ({fix(m.group('e'))}):")
        elif kind == "else":
            out.append(f"{pad}else:")
        elif kind == "halt":
            out.append(f"{pad}_S({number}); raise Halted()")
        elif kind == "assign":
            out.append(f"{pad}_S({number}); {m.group('name')} = {fix(m.group('e'))}")
        elif kind == "setitem":
            out.append(f"{pad}_S({number}); {m.group('name')}[{m.group('i')}] = {fix(m.group('e'))}")
        elif kind == "return":
            out.append(f"{pad}_S({number}); return {fix(m.group('e'))}")
        else:
            out.append(f"{pad}_S({number}); {fix(m.group('e'))}")
    return "\n".join(out) + "\n"


def _to_str(value) -> str:
    """URScript's text of a value (str_cat, textmsg): lists as [a, b, …], numbers as the controller prints them."""
    if isinstance(value, str):
        return value
    if isinstance(value, list | tuple):
        return "[" + ", ".join(map(_to_str, value)) + "]"
    if isinstance(value, bool):
        return str(value)
    return f"{float(value):.6g}" if not isinstance(value, int) else str(value)


def _pow(base, exponent):
    try:
        return math.pow(base, exponent)
    except OverflowError:
        return math.inf


def load(script: str, float32: bool = False) -> dict:
    """Translate and execute the script's top level; returns its namespace (functions, lc_ constants, ``stats``).

    float32: literals and built-in results are numpy float32 (the controller's precision); otherwise Python floats.
    """
    code = translate(script, float32)
    stats = Stats()
    if float32:
        F = np.float32

        def wrap(f):
            return lambda *a: F(f(*(float(x) for x in a)))

        names = {k: wrap(f) for k, f in {"sin": math.sin, "cos": math.cos, "sqrt": math.sqrt}.items()}
        names.update({"atan2": wrap(math.atan2), "pow": wrap(_pow), "_F": F})
    else:
        names = {"sin": math.sin, "cos": math.cos, "sqrt": math.sqrt, "atan2": math.atan2, "pow": _pow}

    def popup(message, title="", warning=False, error=False, blocking=False):
        stats.messages.append(("popup", message))

    names.update(
        {
            "popup": popup,
            "textmsg": lambda *a: stats.messages.append(("textmsg", "".join(map(_to_str, a)))),
            "str_cat": lambda a, b: _to_str(a) + _to_str(b),
            "sync": stats.sync,
            "movej": lambda q, a=1.4, v=1.05, t=0, r=0: stats.messages.append(("movej", [float(x) for x in q])),
            "_S": stats.step,
            "Halted": Halted,
            "stats": stats,
            "__builtins__": {},
        }
    )
    with np.errstate(over="ignore"):
        exec(compile(code, "<urscript>", "exec"), names)
    return names
