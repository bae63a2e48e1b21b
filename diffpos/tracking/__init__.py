"""The per-responder tracker: state, motion/IMM, measurement model, links, SNR, dormant hypotheses, initialisation, with their compiled kernels."""
