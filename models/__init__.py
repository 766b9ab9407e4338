"""armfusion: models layer (kinematics, sensor models, effects, simulator)."""
