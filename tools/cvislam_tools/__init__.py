"""What the analysis scripts share: pose maths (poses), the run outputs' file formats (files) and cvislam_eval
(evaluation). Standard library only.

The scripts in tools/ import it directly (Python puts a script's own folder on the path); scripts elsewhere put
tools/ on sys.path first."""
