"""What every service shares: zenoh transport, service lifecycle, clocks, config, logging, metrics, the JACO-2
model (:mod:`services.common.jaco2`) and frame math (:mod:`services.common.frames`)."""
