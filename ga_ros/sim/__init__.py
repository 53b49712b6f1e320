"""ROS-free simulators of the paper's experiments (deterministic given a seed).

* :mod:`ga_ros.sim.trajectories`: the four synthetic trajectories of Sec. V-A;
* :mod:`ga_ros.sim.aerial`: the aerial lawnmower survey of Sec. IV (motions only);
* :mod:`ga_ros.sim.noise`: Gaussian noise as a percentage of the true motion;
* :mod:`ga_ros.sim.scenario`: the common :class:`~ga_ros.sim.scenario.Scenario` type (ground
  truth, node and track ids, 70 % footprint-overlap connections, F2F);
* :mod:`ga_ros.sim.stereo`: rendered stereo images of the aerial experiment (Sec. V-B).
"""
