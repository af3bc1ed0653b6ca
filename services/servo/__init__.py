"""One servo task (``mfvs servo``): its scenario (:mod:`.scenario`), the run through a stack (:mod:`.run`), what
watches it (:mod:`.watcher`), when it ends (:mod:`.termination`, pure), its log and result (:mod:`.result`) and its
figures (:mod:`.figures`)."""
