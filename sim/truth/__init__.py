"""The simulated world: the true targets, their kinds of motion, the DF sensor models, generated missions."""
