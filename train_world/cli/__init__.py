"""Command-line entry points of ``train_world``: argument parsing and ``main()`` only; the work is done by
the library modules they call. One module per console script (``synth`` = ``dsg-synth``, ``importer`` =
``dsg-import``, ``train`` = ``dsg-train``, ``eval`` = ``dsg-eval``, ``suite`` = ``dsg-suite``, ``import_ply``
= ``dsg-import-ply``, ``compact`` = ``dsg-compact``) plus ``python -m`` tools (``baselines``, ``geom_world``,
``refine``)."""
