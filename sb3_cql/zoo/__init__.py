"""RL-Zoo3 integration: ``cql``, the Panda tasks, our hyperparameter files and the CQL search space in the zoo.

RL-Zoo3 has no plugin mechanism (``ALGOS`` is read for ``--algo`` before ``--gym-packages`` are imported), so the
installed package puts ``sb3_cql-zoo.pth`` in site-packages. At interpreter start-up it only adds an import hook
(:mod:`sb3_cql.zoo.hook`, standard library only); the hook runs :mod:`sb3_cql.zoo.plugin` when, and only when,
``rl_zoo3`` itself is imported. ``import sb3_cql.zoo.plugin`` does the same by hand (e.g. where ``.pth`` files are
not processed).
"""
