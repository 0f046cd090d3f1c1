# Thin aliases for the scripts the README names.
.PHONY: demo test venv bench reproduce
venv:
	scripts/setup_venv.sh
demo:
	scripts/demo.sh
test:
	scripts/test.sh
bench: venv
	.venv/bin/python -m pip install --quiet -r benchmarks/requirements.txt
	.venv/bin/python -m benchmarks.run
reproduce: venv
	.venv/bin/bcid reproduce all
