"""The outdoor-to-indoor channel: emulator, its slot builders, GTD/UTD, link budget, power ratio, and their compiled kernels."""
