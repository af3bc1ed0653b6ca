"""Starting a stack: the profiles and the launcher behind ``mfvs up``/``down``/``status`` (:mod:`.launcher`), a
local stack of processes for one run (:mod:`.local`), the same services composed in one process for lockstep runs
(:mod:`.composed`), and processes kept warm between runs (:mod:`.warm_start`)."""
