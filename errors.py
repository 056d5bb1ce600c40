"""mst.errors: the error types every stage raises, reported by the CLI as one line and exit 1.

Imports the standard library only. The hierarchy::

    MstError                 anything the CLI reports as one line (no traceback), exit 1
    +-- InputError           a bad input or output file: carries ``path`` and ``problem``
    +-- ConfigError          a bad configuration value: carries ``field`` (dotted, e.g.
                             ``slam.fb_max_px``), ``problem`` and the ``source`` it came from

Solvers do not raise for control flow: they return a status (see :class:`SolveStatus`), and an
exception means a bug or bad input, never "no pose this frame".
"""

from __future__ import annotations

import enum
import os


class MstError(Exception):
    """An error the CLI reports as one line (no traceback) with a non-zero exit."""

    exit_code = 1


class InputError(MstError):
    """Bad input: names the offending file and the problem.

    >>> str(InputError("clicks.txt", "3 clicks, need at least 4"))
    'clicks.txt: 3 clicks, need at least 4'
    """

    def __init__(self, path: str | os.PathLike | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class ConfigError(MstError):
    """A bad configuration value: names the field (dotted path), the problem and where it came from.

    ``source`` is the config file, preset or settings file the value came from (``None``: the
    library's caller). The CLI replaces a field that one of its options sets by that option's name
    (:func:`mst.cli.common.config_error_message`).

    >>> str(ConfigError("slam.fb_max_px", "must be > 0, got -1", source="run.yaml"))
    'run.yaml: slam.fb_max_px: must be > 0, got -1'
    """

    def __init__(self, field: str, problem: str, source: str | os.PathLike | None = None):
        self.field = field
        self.problem = problem
        self.source = None if source is None else str(source)
        where = f"{self.source}: " if self.source else ""
        super().__init__(f"{where}{field}: {problem}")

    def with_source(self, source: str | os.PathLike | None) -> ConfigError:
        """The same error attributed to ``source`` (kept when one is already set)."""
        return self if self.source or source is None else ConfigError(self.field, self.problem, source)


class SolveStatus(enum.Enum):
    """Outcome of a solver call (pose solvers return it instead of raising to mean "no pose")."""

    OK = "ok"
    TOO_FEW = "too_few"          #: fewer measurements than unknowns need
    DEGENERATE = "degenerate"    #: the normal equations are singular / not finite
    DIVERGED = "diverged"        #: the iteration left the valid domain (e.g. behind the camera)
