"""eyefem: a differentiable 3-D finite element simulator of scleral buckling surgery in JAX.

The public API, loaded on first use (``import eyefem`` imports nothing else, so it neither
imports JAX nor changes its configuration; see docs/api.md):

- ``simulate(case, design=None, *, mesh=None)``: outcomes of a rigid-buckle surgery case,
  differentiable in the design under jax.grad / jax.jacrev / jax.jit (eyefem.api).
- ``Simulation(case, *, mesh=None)``: one surgery case on one mesh level held by the
  caller; ``sim(design)`` is simulate's outcomes, and it keeps its own warm starts.
- ``load_case(path)``: read and validate a case file (eyefem.io.casefile.Case).
- ``DESIGN_VARIABLES``, ``OUTCOMES``: name -> description (units) of the design variables
  and outcomes simulate() takes and returns.
- ``Mesh`` (eyefem.fem.mesh), ``materials`` (module eyefem.fem.materials), ``terms``
  (module eyefem.fem.terms): the finite-element building blocks.
- ``solve``: the solver sub-package; ``eyefem.solve.solve(model, stages)`` is the Newton
  load path (eyefem.solve.solver.solve). It is the sub-package, not the function, because
  Python binds ``eyefem.solve`` to the sub-package as soon as any of its modules is imported.
- ``Stage``, ``NewtonOptions``: a load stage and the Newton settings.
- ``__version__``: the installed package's version ("0+unknown" when not installed).
"""

_PUBLIC = {  # name -> (module, attribute; None: the module itself)
    "simulate": ("eyefem.api", "simulate"),
    "Simulation": ("eyefem.api", "Simulation"),
    "load_case": ("eyefem.api", "load_case"),
    "DESIGN_VARIABLES": ("eyefem.eye.variables", "DESIGN_VARIABLES"),
    "OUTCOMES": ("eyefem.eye.variables", "OUTCOMES"),
    "Mesh": ("eyefem.fem.mesh", "Mesh"),
    "materials": ("eyefem.fem.materials", None),
    "terms": ("eyefem.fem.terms", None),
    "solve": ("eyefem.solve", None),
    "Stage": ("eyefem.solve.solver", "Stage"),
    "NewtonOptions": ("eyefem.solve.solver", "NewtonOptions"),
}

__all__ = [
    "DESIGN_VARIABLES",
    "OUTCOMES",
    "Mesh",
    "NewtonOptions",
    "Simulation",
    "Stage",
    "__version__",
    "load_case",
    "materials",
    "simulate",
    "solve",
    "terms",
]


def __getattr__(name: str):
    """PEP 562: import a public name on first use."""
    import importlib

    if name == "__version__":
        from importlib import metadata

        try:
            return metadata.version("eyefem")
        except metadata.PackageNotFoundError:
            return "0+unknown"
    if name not in _PUBLIC:
        raise AttributeError(f"module 'eyefem' has no attribute '{name}'; the public API is "
                             f"{', '.join(__all__)}")
    module, attribute = _PUBLIC[name]
    mod = importlib.import_module(module)
    return mod if attribute is None else getattr(mod, attribute)


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
