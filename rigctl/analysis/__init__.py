"""The application layer: turns a recording (or arrays read from one) into result objects.

Between the command-line / daemon / report layer, which only parse, call and present, and the
pure solvers (:mod:`rigctl.solvers`, functions of arrays with no I/O): the pipelines that read
a recording, choose and run solvers, and return typed results. See docs/architecture.md.
"""
