# lidarcal: `make report` and `make test` work on a fresh machine (they build .venv).
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
DATA := data/paper_rig
OUT := reports/calibration

.PHONY: install test report bench data notebooks clean lint study lab

install: $(STAMP)

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip uv
	$(BIN)/uv pip install --quiet --python $(BIN)/python -e '.[dev]'
	$(BIN)/python -m ipykernel install --sys-prefix --name python3 >/dev/null
	-$(BIN)/python -m compileall -q -j 2 $(VENV)/lib >/dev/null 2>&1
	-$(BIN)/python -m compileall -q lidarcal >/dev/null 2>&1
	@touch $(STAMP)

test: $(STAMP)
	MPLBACKEND=Agg $(BIN)/python -m pytest -n 2 --dist loadfile tests notebooks --nbval-lax -p no:cacheprovider

report: $(STAMP)
	MPLBACKEND=Agg $(BIN)/lidarcal calibrate $(DATA) --out $(OUT)
	MPLBACKEND=Agg $(BIN)/lidarcal measure $(DATA) --calibration $(OUT)/calibration.json --out $(OUT)
	MPLBACKEND=Agg $(BIN)/lidarcal report $(DATA) --calibration $(OUT)/calibration.json \
		--measurements $(OUT)/measurements.json --out reports/calibration-report.pdf
	MPLBACKEND=Agg $(BIN)/lidarcal workbook $(DATA) --out reports/workbook.pdf
	MPLBACKEND=Agg $(BIN)/lidarcal planes data/real_tapas --pattern 8x5 --square-mm 100 \
		--camera data/real_tapas/camera.json --out reports/real_tapas
	MPLBACKEND=Agg $(BIN)/lidarcal workbook data/real_tapas --out reports/workbook-real.pdf
	MPLBACKEND=Agg $(BIN)/lidarcal report data/real_tapas --out reports/real_tapas/report.pdf
	@echo "wrote reports/calibration-report.pdf, reports/workbook.pdf (the turntable rig) and"
	@echo "reports/workbook-real.pdf, reports/real_tapas/ (one flat board, real data: report.pdf)"

lab: $(STAMP)  # JupyterLab on the workbook (set DATASET in each notebook's first code cell)
	$(BIN)/jupyter lab notebooks

data: $(STAMP)
	$(BIN)/lidarcal simulate $(DATA) --seed 0 --rig paper --overwrite

study: $(STAMP)
	$(BIN)/python -m lidarcal.study --full reports/study.csv
	$(BIN)/python -m lidarcal.study --ranging reports/study_ranging.csv

bench: $(STAMP)
	@# bytecode as a pip install leaves it (the editable install never writes it when
	@# PYTHONDONTWRITEBYTECODE is set: every run would compile the package, ~50 ms)
	-$(BIN)/python -m compileall -q lidarcal >/dev/null 2>&1
	$(BIN)/python scripts/bench.py $(DATA)

lint: $(STAMP)
	$(BIN)/ruff check lidarcal tests scripts

clean:
	rm -rf $(VENV) reports/calibration
