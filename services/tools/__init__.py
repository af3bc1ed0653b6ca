"""python-can interfaces that carry the emulated RS-485 bus where no physical bus is: ``mfvs_hub``, a loopback CAN
hub between processes (``mfvs bus-hub``), and ``mfvs_local``, a bus between threads of one process."""
