"""RL-Zoo3 integration: ``sb3_cql-zoo.pth`` adds an import hook (:mod:`sb3_cql.zoo.hook`, standard library only) that
imports :mod:`sb3_cql.zoo.plugin`, which registers our algorithms, tasks, configs and search spaces, with ``rl_zoo3``."""
