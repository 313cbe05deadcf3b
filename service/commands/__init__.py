"""The service's subcommands of the one ``falcon-plan`` command line: ``serve``, ``request``,
``demo`` and ``router``.

The library (:mod:`falcon_plan`) knows nothing of them: each module's ``register`` function is
declared in pyproject.toml under the entry-point group ``falcon_plan.commands``, which
:func:`falcon_plan.cli.build_parser` reads at start-up. The application thus plugs its commands
into the library's parser, and the dependency runs one way, from ``service`` to ``falcon_plan``.
"""
