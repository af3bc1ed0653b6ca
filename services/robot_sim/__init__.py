"""robot_sim: a MuJoCo JACO-2 7-DoF behind the emulated Kinova DSP, with an eye-in-hand camera."""
