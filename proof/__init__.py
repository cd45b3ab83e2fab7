"""The blind proof of the discrepancy analyser (``compasscal prove``, benchmarks/discrepancy.py).

- :mod:`proof.concealments`: physics outside the catalogue (offsets in time windows in each frame,
  gain following temperature, drifting misalignment, intermittent interference) as concealment classes;
- :mod:`proof.generator`: the cases (catalogue effects, pairs, nulls and the open-world kinds), each
  effect sized by its non-centrality; never imports the analyser;
- :mod:`proof.runner`: tasks, worker processes (one BLAS thread each) and :func:`proof.runner.run_proof`;
  the only module that imports the analyser, in the worker;
- :mod:`proof.score`: the scorer and the report tables.

It lives outside physics/ because it spawns processes and sets environment variables; physics/ stays pure.
"""
