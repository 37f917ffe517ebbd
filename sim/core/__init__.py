"""The project's infrastructure, the lowest layer: sim, learn and register import it, and it imports
nothing of the project but itself.

- :mod:`sim.core.errors`: the error types a user can act on (one line, no traceback);
- :mod:`sim.core.atomic`: atomic writes of files, folders, JSON, figures; folder locks;
- :mod:`sim.core.cliargs`: command-line options declared once on dataclasses (bounds, help);
- :mod:`sim.core.outputs`: output files and folders checked before the work;
- :mod:`sim.core.progress`: progress lines with rate and ETA, stage clocks;
- :mod:`sim.core.seeds`: every random stream derived from one seed and a kind;
- :mod:`sim.core.scale`: Dask clusters (``local:N``, ``tcp://``) and their scheduler files.
"""
