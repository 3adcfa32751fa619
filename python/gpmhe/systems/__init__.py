"""Example plants: those of the two papers (simulators and training-data collection) and two
physics models.

* `gpmhe.systems.batch_reactor`: the batch reactor 2A -> B of the GP-MHE paper (model, simulator,
  the offline training trajectories and the paper's MHE settings);
* `gpmhe.systems.second_order`: the second-order plant with a hidden disturbance z(ζ) of the
  RGP-dKF paper (scenarios S1–S3, the RGP-dKF and the RGP-B baseline);

and two continuous-time physics models, sampled by `gpmhe.discretize` (numpy or CasADi):

* `gpmhe.systems.rotating_masses`: three discs between two motors, do-mpc's moving-horizon
  estimation example (the inertia Θ1 as a parameter);
* `gpmhe.systems.cart_pole`: the cart-pole, all states measured, in a near-deterministic MHE
  setting.

See the user guide, *Example systems*.
"""
