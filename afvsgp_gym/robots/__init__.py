"""The bridge to a real Franka arm: sphere kinematics, barrier terms from the robot's model,
a 1 kHz torque loop through libfranka's interface and a MuJoCo-backed stand-in for dry runs
(numpy only at import; the stand-in imports MuJoCo, the robot pylibfranka, when built)."""
