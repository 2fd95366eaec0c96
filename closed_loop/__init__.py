"""The closed loop around the service, from the outside: clients of ``tupa serve``, not part
of it.

- :mod:`closed_loop.controller`: the simulated network controller. It plays the network: reads
  the vehicle's true position, computes every user's throughput, delay and loss there with the
  embedded model, and POSTs them as reports, as a real controller would.
- :mod:`closed_loop.demo`: ``tupa demo`` (``make run``): starts a sitl-mock and ``tupa serve``
  per compared policy, drives them with the controller, and writes the tables and figures.
- :mod:`closed_loop.fleet_controller`, :mod:`closed_loop.fleet_demo`: the same for a fleet
  (``tupa demo --uavs K``): one report of all users measured with the fleet model at every
  vehicle's true position.
- :mod:`closed_loop.processes`: starting ``tupa serve`` and ``tupa sitl-mock`` as child
  processes on free loopback ports (the demo, the end-to-end tests and the benchmarks use it),
  one mock per vehicle of a fleet, and the fleet file that matches them.
- :mod:`closed_loop.cli`: the ``demo`` and ``controller-sim`` subcommands.
"""
