"""Speed benchmarks, one module per area, each with ``run(quick=False) -> dict`` and ``main()``:
what ``afvsgp-gym bench`` runs (the experiment tools are in the repository's benchmarks/).

- :mod:`afvsgp_gym.benchmarks.gp`: learner update / prediction times.
- :mod:`afvsgp_gym.benchmarks.envs`: environment steps per second.
- :mod:`afvsgp_gym.benchmarks.filter`: SOCP and full filtered-step times (and, in full, the
  acceptance sweeps).
- :mod:`afvsgp_gym.benchmarks.arm`: the whole-arm filtered step against the number of barriers.
- :mod:`afvsgp_gym.benchmarks.solver`: the filter's cone program against cbfpy and clarabel.
- :mod:`afvsgp_gym.benchmarks.sweep`: the sweep executors' overhead.
- :mod:`afvsgp_gym.benchmarks.run_all`: all of them in one run (``afvsgp-gym bench``).
"""
