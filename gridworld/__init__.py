"""Minimize surprise on a torus grid: the self-assembly scenario of paper Sec. III-IV.

N agents live on a W x H torus, one per cell, each looking at 14 (or 6 or 8) cells around it,
moving one cell forward or turning on the spot. Their actor-predictor pair
(:mod:`minimize_surprise.gridnet`) is evolved by a genetic algorithm
(:mod:`minimize_surprise.genetic`) to make the swarm's sensor readings predictable; what forms is
classified into nine patterns.

Modules: :mod:`gridworld.world` (geometry, sensor models, start configurations),
:mod:`gridworld.kernels`, :mod:`gridworld.runs` and :mod:`gridworld.evaluate` (compiled simulation
of whole generations), :mod:`gridworld.predictor` and :mod:`gridworld.simd` (the predictor's
step on vectors of lanes, written as LLVM intrinsics),
:mod:`gridworld.patterns` (the nine patterns and solution quality), :mod:`gridworld.config`,
:mod:`gridworld.evolve` (a run with checkpoints), :mod:`gridworld.qd` and
:mod:`gridworld.qd_plots` (MAP-Elites over pattern measures, through pyribs),
:mod:`gridworld.tasks` (the studies' entry point), :mod:`gridworld.plots`,
:mod:`gridworld.figures` and :mod:`gridworld.cli` (``surprise-grid``). docs/gridworld.md
describes the scenario and every choice made.
"""
