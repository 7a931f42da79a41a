"""Why does the model disagree with the robot? Logs, an effect library, held-out selection of the missing effects,
compare/diagnose and its command line (`python rme.py diagnose LOG`), and simulated excitation logs."""
