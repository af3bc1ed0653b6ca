"""mfvs services: thin zenoh adapters around plain, importable algorithms."""
