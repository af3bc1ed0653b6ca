"""Commissioning: what a host can sustain (``mfvs doctor``, :mod:`.doctor`) and whether an arm and its bus answer
as they should before anyone relies on them (``mfvs check arm|rs485``, :mod:`.check`)."""
