"""controller: the visual servo control laws of seeds 000, 002 and 004, and the service that runs one of them."""
