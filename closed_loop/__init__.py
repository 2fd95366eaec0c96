"""The closed loop around the service, from the outside: clients of ``tupa serve``, not part
of it.

- :mod:`closed_loop.controller`: the simulated network controller. It plays the network: reads
  the vehicle's true position, computes every user's throughput, delay and loss there with the
  embedded model, and POSTs them as reports, as a real controller would.
- :mod:`closed_loop.demo`: ``tupa demo`` (``make run``): starts a sitl-mock and ``tupa serve``
  per compared policy, drives them with the controller, and writes the tables and figures.
- :mod:`closed_loop.processes`: starting ``tupa serve`` and ``tupa sitl-mock`` as child
  processes on free loopback ports (the demo, the end-to-end tests and the benchmarks use it).
- :mod:`closed_loop.cli`: the ``demo`` and ``controller-sim`` subcommands.
"""
