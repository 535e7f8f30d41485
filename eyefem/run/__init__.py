"""Running a problem: its load path solved, its results written as it goes
(:mod:`eyefem.run.runner`)."""
