# Thin aliases for the scripts the README names.
.PHONY: demo test venv bench reproduce
venv:
	scripts/setup_venv.sh
demo:
	scripts/demo.sh
test:
	scripts/test.sh
bench: venv
	.venv/bin/python benchmarks/run.py
reproduce: venv
	.venv/bin/bcid reproduce all
