"""Spoken answers: which words count as a yes or a no (:mod:`app.speech.vocabulary`), shared by
the robot bridges (the robot's own recogniser) and the room's offline recogniser."""
