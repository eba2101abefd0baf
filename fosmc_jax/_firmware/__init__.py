"""From the bench to the drive: the tuned controller exported as C (:mod:`.export`) and the arm's
parameters identified from a log (:mod:`.identify`)."""
