"""The guidance predictor: Problem P1 solved without a mixed-integer solver."""
