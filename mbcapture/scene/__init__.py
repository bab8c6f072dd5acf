"""What is in front of the camera: the scene registry, camera and object motion, the camera frame, the lens, the metronome's pendulum."""
