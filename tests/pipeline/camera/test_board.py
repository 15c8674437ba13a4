import re

import cv2
import numpy as np
import OpenImageIO as oiio
import pytest

from pipeline.camera.board import BoardDetector, page_layout
from pipeline.cli import main
from pipeline.core.sections import BoardSection


@pytest.mark.parametrize("kind", ["charuco", "checkerboard"])
def test_the_printed_board_is_detected_with_every_corner(kind, tmp_path):
    assert main(["board", "--out", str(tmp_path / "board"), "--dpi", "100", "-s", f"board.kind={kind}"]) == 0
    pattern = cv2.imread(str(tmp_path / "board.png"), cv2.IMREAD_GRAYSCALE)
    # A photo of a print: white paper around the pattern, slightly out of focus.
    photo = cv2.GaussianBlur(cv2.copyMakeBorder(pattern, 60, 60, 60, 60, cv2.BORDER_CONSTANT, value=255), (0, 0), 1.0)
    board = BoardSection(kind=kind)
    found = BoardDetector(board).detect(photo)
    assert found is not None and len(found.ids) == (board.squares_x - 1) * (board.squares_y - 1)
    # Corner k sits where the board geometry says: squares of round(30 mm at 100 dpi) pixels,
    # and a corner between pixels i-1 and i lies at i - 0.5 in OpenCV's pixel-centre convention.
    pixels_per_square = round(30 / 25.4 * 100)
    expected = found.object_points[:, :2] / 0.030 * pixels_per_square - 0.5
    np.testing.assert_allclose(found.image_points - 60, expected, atol=0.2)


def test_png_and_pdf_have_the_physical_size(tmp_path):
    assert (
        main(["board", "--out", str(tmp_path / "board"), "-s", "board.square_mm=25", "-s", "board.marker_mm=18"]) == 0
    )
    spec = oiio.ImageInput.open(str(tmp_path / "board.png")).spec()
    assert spec.getattribute("XResolution") == pytest.approx(300)
    assert spec.width == 7 * round(25 / 25.4 * 300)
    media_box = re.search(rb"MediaBox \[ 0 0 ([\d.]+) ([\d.]+) \]", (tmp_path / "board.pdf").read_bytes())
    width_pt, height_pt = (float(v) for v in media_box.groups())
    # 175 x 125 mm fits an upright A4 page with its margins.
    assert (width_pt, height_pt) == pytest.approx((210 / 25.4 * 72, 297 / 25.4 * 72), abs=0.1)


def test_page_layout_centres_the_board_and_refuses_what_does_not_fit():
    page, (left, _) = page_layout(BoardSection(squares_x=5, squares_y=7), "A4")
    assert page == (210.0, 297.0) and left == pytest.approx((210 - 150) / 2)
    with pytest.raises(ValueError, match="does not fit on A4"):
        page_layout(BoardSection(squares_x=12, squares_y=9), "A4")


def test_a_board_too_large_for_the_paper_is_a_config_error(tmp_path, capsys):
    assert main(["board", "--out", str(tmp_path / "board"), "-s", "board.squares_x=12", "-s", "board.squares_y=9"]) == 2
    assert "larger --paper" in capsys.readouterr().err


@pytest.mark.parametrize(
    "argv, message",
    [
        (["-s", "board.squares_x=20", "-s", "board.squares_y=20"], "hold 200 markers, but board.dictionary"),
        (
            [
                "--paper",
                "A3",
                "--dpi",
                "2400",
                "-s",
                "board.squares_x=5",
                "-s",
                "board.squares_y=3",
                "-s",
                "board.square_mm=75",
            ],
            "megapixels at 2400 dpi, more than any printer resolves: choose --dpi",
        ),
        (["--out", "FILE/board"], "cannot write into"),
    ],
    ids=["too-many-markers", "too-many-pixels", "out-inside-a-file"],
)
def test_a_board_that_cannot_be_made_is_refused_with_the_fix(tmp_path, capsys, argv, message):
    (tmp_path / "FILE").write_text("x")
    argv = [str(tmp_path / a) if a.startswith("FILE") else a for a in argv]
    out = [] if "--out" in argv else ["--out", str(tmp_path / "board")]
    assert main(["board", *out, *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and not (tmp_path / "board.png").exists()


def test_an_existing_board_is_replaced_only_when_asked(tmp_path, capsys):
    out = tmp_path / "board"
    assert main(["board", "--out", str(out), "--dpi", "72"]) == 0
    (tmp_path / "board.pdf").write_bytes(b"a board someone printed from")
    assert main(["board", "--out", str(out), "--dpi", "72"]) == 2
    err = capsys.readouterr().err
    assert "board.png and" in err and "add --force to replace them" in err
    assert (tmp_path / "board.pdf").read_bytes() == b"a board someone printed from"
    assert main(["board", "--out", str(out), "--dpi", "72", "--force"]) == 0
    assert (tmp_path / "board.pdf").read_bytes().startswith(b"%PDF")
