"""Cutting an exercise out of a notebook: every honest way of writing it runs as it does in the notebook.

Each variant of the catalogue is a notebook (its code cells, then the exercise's check cell). The
notebook is run as Jupyter would run it (cell after cell in one namespace); then the exercise is
cut out (:func:`extract_exercise`), run alone in a fresh module, and called with the same
arguments: it must return the same result, with no problem noted. Statements that the exercise
does not need (demos, plots, prints) must stay out of what is cut.
"""

from __future__ import annotations

import textwrap
from dataclasses import dataclass

import nbformat
import numpy as np
import pytest

from course_lib.instructor.extract import extract_exercise
from course_lib.instructor.notebooks import python_source


@dataclass
class Variant:
    id: str
    cells: list[str]
    args: tuple = (np.arange(3.0),)
    name: str = "solve"
    left_out: tuple[str, ...] = ()  # text that must not be in the extracted code


SOLVE_K = "def solve(x):\n    return x * K\n"

CATALOGUE = [
    # item and attribute assignment
    Variant("item assignment", ['OPTS = {"scale": 2.0}\nOPTS["sign"] = -1.0',
                                'def solve(x):\n    return OPTS["sign"] * OPTS["scale"] * x']),
    Variant("item assignment on one line", ['OPTS = {"scale": 2.0}; OPTS["sign"] = -1.0; UNUSED = 7',
                                            'def solve(x):\n    return OPTS["sign"] * OPTS["scale"] * x'],
            left_out=("UNUSED",)),
    Variant("item assignment in a later cell", ['OPTS = {"sign": 1.0}',
                                                'def solve(x):\n    return OPTS["sign"] * x',
                                                'OPTS["sign"] = -3.0']),
    Variant("nested item assignment", ['CFG = {"a": {"b": 1.0}}\nCFG["a"]["b"] = 4.0',
                                       'def solve(x):\n    return CFG["a"]["b"] + x']),
    Variant("attribute assignment", ['class Cfg:\n    pass\n\ncfg = Cfg()\ncfg.scale = 3.0\ncfg.offset = 1.0',
                                     'def solve(x):\n    return cfg.scale * x + cfg.offset']),
    Variant("alias changed later", ['BASE = {"a": 1.0}\nOPTS = BASE\nBASE["a"] = 5.0',
                                    'def solve(x):\n    return OPTS["a"] * x']),
    Variant("method call that changes a value", ['WEIGHTS = [1.0]\nWEIGHTS.append(2.0)\nWEIGHTS.extend([3.0])',
                                                 'def solve(x):\n    return x * sum(WEIGHTS)']),
    Variant("dict update", ['OPTS = dict(sign=1.0)\nOPTS.update(sign=-2.0)',
                            'def solve(x):\n    return OPTS["sign"] * x']),
    Variant("table filled by a loop", ['TABLE = {}\nfor k in range(3):\n    TABLE[k] = k * k',
                                       'def solve(x):\n    return x + TABLE[2]']),
    # augmented assignment
    Variant("augmented assignment", ['SCALE = 1.0\nSCALE *= 3', 'COUNTS = [0]\nCOUNTS[0] += 2',
                                     'def solve(x):\n    return SCALE * x + COUNTS[0]']),
    Variant("augmented attribute", ['import numpy as np\nclass P:\n    w = np.ones(3)\nP.w += 1',
                                    'def solve(x):\n    return P.w * x']),
    # decorators
    Variant("library decorator", [('import functools\n\n@functools.lru_cache(maxsize=None)\ndef weight(k):\n'
                                  '    return 2.0 ** k'),
                                  'def solve(x):\n    return x * weight(3)']),
    Variant("notebook decorator", [('FACTOR = 2.0\n\ndef doubled(fn):\n    def wrapper(*a):\n'
                                   '        return FACTOR * fn(*a)\n    return wrapper'),
                                   '@doubled\ndef solve(x):\n    return x + 1']),
    Variant("decorator with arguments", [('def scaled(s):\n    def deco(fn):\n        return lambda *a: s * fn(*a)\n'
                                         '    return deco\nS = 4.0'),
                                         '@scaled(S)\ndef solve(x):\n    return x']),
    Variant("rewrapped after the def", ['def twice(fn):\n    return lambda x: fn(fn(x))',
                                        'def solve(x):\n    return x + 1\n\nsolve = twice(solve)']),
    # nested defs and scopes
    Variant("nested def reads a constant", ['K = 5.0', ('def solve(x):\n    def inner(y):\n        return y * K\n'
                                            '    return inner(x)')]),
    Variant("name local to a nested def only", ['N = 10.0', ('def solve(x):\n    def g():\n        N = 2.0\n'
                                                '        return N\n    return g() + N + x')]),
    Variant("closure over a local", ['OFFSET = 1.0', ('def solve(x):\n    s = 3.0\n    def f(v):\n'
                                     '        return v * s + OFFSET\n    return f(x)')]),
    Variant("class in a def", ['BIAS = 0.5', ('def solve(x):\n    class Acc:\n        b = BIAS\n'
                               '        def add(self, v):\n            return v + self.b\n    return Acc().add(x)')]),
    Variant("recursion", ['BASE_CASE = 1', 'def solve(n):\n    return BASE_CASE if n <= 1 else n * solve(n - 1)'],
            args=(5,)),
    # global
    Variant("global counter", ['COUNTER = 0', ('def solve(x):\n    global COUNTER\n    COUNTER += 1\n'
                                              '    return x + COUNTER')]),
    Variant("global set by a setup function", ['def setup():\n    global K\n    K = 5.0\n\nsetup()', SOLVE_K]),
    Variant("global changed in place by a function", [('OPTS = {"sign": 1.0}\n\ndef configure():\n'
                                                      '    OPTS["sign"] = -2.0\n\nconfigure()'),
                                                      'def solve(x):\n    return OPTS["sign"] * x']),
    Variant("global at top level", ['global K\nK = 2.0', SOLVE_K]),
    # lambdas
    Variant("lambda helper", ['square = lambda v: v * v', 'def solve(x):\n    return square(x) + 1']),
    Variant("lambda default captures a constant", ['S = 3.0\nscale = lambda v, s=S: v * s\nS = 100.0',
                                                   'def solve(x):\n    return scale(x)']),
    Variant("lambda inside", ['P = 2', 'def solve(x):\n    f = lambda v: v ** P\n    return f(x)']),
    # classes
    Variant("class exercise", ['import numpy as np\nK = 2.0',
                               ('class Solve:\n    factor = K\n\n    def __init__(self, bias=1.0):\n'
                               '        self.bias = bias\n\n    def __call__(self, x):\n'
                               '        return self.factor * np.asarray(x) + self.bias')],
            name="Solve", args=()),
    Variant("class with a notebook base class", ['class Base:\n    def scale(self):\n        return 3.0',
                                                 ('class Solve(Base):\n    def __call__(self, x):\n'
                                                 '        return self.scale() * x')],
            name="Solve", args=()),
    Variant("dataclass of options", [('from dataclasses import dataclass\nSCALE = 2.0\n\n@dataclass\nclass Params:\n'
                                     '    scale: float = SCALE\n    shift: float = 0.5\n\nPARAMS = Params()\n'
                                     'PARAMS.shift = 1.5'),
                                     'def solve(x, p=PARAMS):\n    return p.scale * x + p.shift']),
    # with, try, if
    Variant("with block", ['import numpy as np\nwith np.errstate(all="ignore"):\n    TABLE = np.log(np.arange(3.0) + 1)',
                           'def solve(x):\n    return x + TABLE']),
    Variant("optional import in try", [('try:\n    from scipy.linalg import norm\nexcept ImportError:\n'
                                       '    from numpy.linalg import norm'),
                                       'def solve(x):\n    return norm(x)']),
    Variant("try in the function", ['FALLBACK = -1.0', ('def solve(x):\n    try:\n        return 1.0 / x[0]\n'
                                    '    except ZeroDivisionError:\n        return FALLBACK')], args=([0.0],)),
    Variant("if chooses a helper", [('FAST = True\nif FAST:\n    def helper(v):\n        return 2 * v\nelse:\n'
                                    '    def helper(v):\n        return 3 * v'),
                                    'def solve(x):\n    return helper(x)']),
    # walrus, unpacking, star imports, annotations
    Variant("walrus at top level", ['if (LIMIT := 4) > 2:\n    pass', 'def solve(x):\n    return x * LIMIT']),
    Variant("walrus in the function", ['T = 0.5', 'def solve(x):\n    return [y for v in x if (y := v * 2) > T]']),
    Variant("tuple and starred unpacking", ['A, B = 1.0, 2.0\nFIRST, *REST = [3.0, 4.0, 5.0]\nC = D = 0.5',
                                            'def solve(x):\n    return A + B + FIRST + sum(REST) + C + D + x']),
    Variant("star import of an allowed module", ['from numpy.linalg import *\nfrom numpy import *',
                                                 'def solve(x):\n    return norm(x) + sqrt(4.0)']),
    Variant("type annotations", ['import numpy as np\nfrom numbers import Number\nSCALE: float = 2.0\nLATER: int',
                                 ('def solve(x: np.ndarray, k: Number = 1) -> np.ndarray:\n'
                                 '    y: np.ndarray = x * SCALE\n    return y + k')]),
    Variant("future annotations", [('from __future__ import annotations\n\nimport numpy as np\n\n'
                                   'def solve(x: Undefined) -> AlsoUndefined:\n    return np.asarray(x) * 2')]),
    # module constants and helpers of earlier cells
    Variant("constants from constants", ['import numpy as np\nA = 2.0\nB = A * 3\nM = np.eye(3) * B', 'A = 100.0',
                                         'def solve(x):\n    return M @ x']),
    Variant("constant rebound after the def", ['SIGN = -1.0', 'def solve(x):\n    return SIGN * x', 'SIGN = 1.0']),
    Variant("helper redefined later", ['def helper(v):\n    return v', 'def solve(x):\n    return helper(x)',
                                       'def helper(v):\n    return 10 * v']),
    Variant("helper chain over cells", ['import numpy as np', 'def centre(p):\n    return p - p.mean()',
                                        'def scale(p):\n    return centre(p) / np.abs(centre(p)).max()',
                                        'def solve(x):\n    return scale(x)']),
    Variant("constant computed by a helper", ['G = 1.0\ndef h():\n    return G\nC = h()\nG = 2.0',
                                              'def solve(x):\n    return x * C + G']),
    Variant("comprehension at top level", ['def sq(i):\n    return i * i\nTABLE = [sq(i) for i in range(4)]',
                                           'def solve(x):\n    return x + TABLE[-1]']),
    Variant("exercise redefined", ['def solve(x):\n    return x', 'def solve(x):\n    return 2 * x']),
    Variant("magics, demos and prints", ['%matplotlib inline\nimport numpy as np\nK = 2.0',
                                         SOLVE_K + '\nDEMO = solve(np.ones(3))\nprint("demo", DEMO)',
                                         '!echo hello\nPLOTTED = [DEMO]'],
            left_out=("DEMO", "print", "PLOTTED", "echo")),
    Variant("seeded rng changed at top level", ['import numpy as np\nRNG = np.random.default_rng(0)\nRNG.normal()',
                                                'NOISE = RNG.normal(size=3)', 'def solve(x):\n    return x + NOISE']),
]


def _notebook(cells: list[str]):
    nb = nbformat.v4.new_notebook()
    nb.cells = [nbformat.v4.new_markdown_cell("# a notebook")]
    nb.cells += [nbformat.v4.new_code_cell(textwrap.dedent(c)) for c in cells]
    nb.cells.append(nbformat.v4.new_code_cell("# NBVAL_CHECK_OUTPUT\ncheck_solve(solve)"))
    return nb


def _run_notebook(nb) -> dict:
    """The namespace after running every cell before the check cell, as a kernel would."""
    ns = {"__name__": "__main__"}
    for cell in nb.cells[:-1]:
        if cell.cell_type == "code":
            exec(compile(python_source(cell.source), "<cell>", "exec"), ns)  # noqa: S102 - the test's own code
    return ns


def _call(ns: dict, v: Variant):
    obj = ns[v.name]
    if isinstance(obj, type):
        return obj()(np.arange(3.0))
    return obj(*v.args)


@pytest.mark.parametrize("variant", CATALOGUE, ids=[v.id for v in CATALOGUE])
def test_the_extracted_exercise_returns_what_the_notebook_returns(variant):
    nb = _notebook(variant.cells)
    expected = _call(_run_notebook(nb), variant)
    ex = extract_exercise(nb, variant.name, len(nb.cells) - 1)
    assert ex is not None and ex.problems == [], ex and ex.problems
    ns = {"__name__": "__main__"}
    exec(compile(ex.code, "<extracted>", "exec"), ns)  # noqa: S102 - the test's own code
    np.testing.assert_array_equal(np.asarray(_call(ns, variant)), np.asarray(expected), err_msg=ex.code)
    for text in variant.left_out:
        assert text not in ex.code, f"{text!r} should not be cut out with the exercise:\n{ex.code}"


def test_the_def_cell_is_the_last_def_and_a_missing_def_gives_none():
    nb = _notebook(["def solve(x):\n    return x", "X = 1", "def solve(x):\n    return 2 * x", "solve = solve"])
    assert extract_exercise(nb, "solve", len(nb.cells) - 1).def_cell == 3
    assert extract_exercise(nb, "other", len(nb.cells) - 1) is None
    assert extract_exercise(_notebook(["solve = lambda x: x"]), "solve", 2) is None


def test_names_no_cell_defines_are_noted():
    nb = _notebook(["def solve(x):\n    return x * NOWHERE + display(x)"])
    (problem,) = extract_exercise(nb, "solve", 2).problems
    assert "NOWHERE" in problem and "display" in problem


def test_cells_after_the_check_cell_and_cells_that_do_not_parse_are_ignored():
    nb = _notebook(["K = 1.0", "def solve(x):\n    return x * K", "K = (", "K = 2.0"])
    nb.cells.insert(len(nb.cells), nbformat.v4.new_code_cell("K = 3.0"))
    ex = extract_exercise(nb, "solve", len(nb.cells) - 2)
    assert "K = 3.0" not in ex.code and "K = 2.0" in ex.code and "K = (" not in ex.code
