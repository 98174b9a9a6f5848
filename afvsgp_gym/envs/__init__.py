"""afvsgp_gym.envs: obstacle-avoidance environments with exact barrier ground truth.

- ``point_mass``: ``PointMassObstacleEnv`` (analytic double integrator, closed-form terms).
- ``franka``: ``FrankaObstacleEnv`` (MuJoCo Panda, torque control, hidden model mismatch).
- ``reach``: ``FrankaObstacleReachEnv`` (the Panda reaching goals past obstacles with
  task-space velocity actions: the reinforcement-learning task).
- ``base``: what every obstacle env shares (the step, the info keys, the barrier cache, the
  arguments' check).
- ``franka_model``: assembling the Panda MJCF from gymnasium_robotics with MjSpec.
- ``mjspec_compat``: MjSpec setters that work on every supported MuJoCo release.
- ``scenario``: reference motions, obstacle trajectories, the sphere barrier's kinematics.
- ``primitives``: exact signed distance from a safety sphere's centre to spheres, boxes,
  capsules and planes, with the normal and curvature a relative-degree-2 barrier needs.
- ``self_collision``: the pairs of safety spheres on the arm's own links and its base that
  can meet, and their barrier terms (numpy); on by default with the arm's spheres.
- ``scenes``: the tabletop (clutter drawn per reset, a moving forearm) and shelf scenes of
  several typed obstacles.
- ``registration``: the Gymnasium ids (string entry points: importing this package does
  not import MuJoCo).
"""
