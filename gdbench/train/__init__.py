"""The reference trainer: configs and presets (``config``), density control (``densify``),
initialisation (``init``), the step (``trainer``), the loop and outputs (``run``, ``outputs``)."""
