from pathlib import Path

import pytest

from perchpose.app.fit_fusion import FitFusionOptions, run
from perchpose.errors import PerchposeError


def test_data_without_the_columns_is_named(tmp_path: Path) -> None:
    data = tmp_path / "data.csv"
    data.write_text("a,b\n1,2\n")
    with pytest.raises(PerchposeError, match=r"data\.csv"):
        run(FitFusionOptions(str(data), json_out=str(tmp_path / "fit.json")))
    assert not (tmp_path / "fit.json").exists()
