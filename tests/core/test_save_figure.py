"""The one figure saver (minimize_surprise.figures): every format written, each at the pixel size
asked for, all at once: a figure failing to draw leaves no file, not even a partial one."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import pytest

from minimize_surprise.figures import DPI, FORMATS, save_figure
from needs import require_module

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _figure(width: float = 4, height: float = 3, dpi: float = 100):
    require_module("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height), dpi=dpi)
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot([0, 1, 2], [1, 0, 1], label="a line")
    ax.set(title="a title", xlabel="x", ylabel="y")
    ax.legend()
    return fig


def _png_size(path: Path) -> tuple[int, int]:
    data = path.read_bytes()
    assert data.startswith(PNG_MAGIC)
    width, height = struct.unpack(">II", data[16:24])  # the IHDR chunk comes first
    return width, height


def test_each_format_is_written_beside_the_stem(tmp_path):
    paths = save_figure(_figure(), tmp_path / "fitness")
    assert (
        paths
        == [tmp_path / f"fitness.{fmt}" for fmt in FORMATS]
        == [
            tmp_path / "fitness.png",
            tmp_path / "fitness.pdf",
        ]
    )
    assert paths[0].read_bytes().startswith(PNG_MAGIC)
    assert paths[1].read_bytes().startswith(b"%PDF")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fitness.pdf", "fitness.png"]


def test_a_dotted_stem_keeps_its_dots(tmp_path):
    (path,) = save_figure(_figure(), tmp_path / "size=0.8", formats=("png",))
    assert path == tmp_path / "size=0.8.png" and path.is_file()


def test_the_pixel_size_is_the_figures_size_times_the_dpi_asked_for(tmp_path):
    fig = _figure(4, 3, dpi=100)
    (path,) = save_figure(fig, tmp_path / "a", formats=("png",), dpi=50, tight=False)
    assert _png_size(path) == (200, 150)
    (path,) = save_figure(fig, tmp_path / "b", formats=("png",), tight=False)
    assert _png_size(path) == (4 * DPI, 3 * DPI)
    # None: matplotlib's own choice, by default the figure's dpi.
    (path,) = save_figure(fig, tmp_path / "c", formats=("png",), dpi=None, tight=False)
    assert _png_size(path) == (400, 300)


def test_tight_crops_to_the_drawing_as_bbox_inches_tight_does(tmp_path):
    fig = _figure(4, 3)
    (path,) = save_figure(fig, tmp_path / "tight", formats=("png",), dpi=120)
    direct = tmp_path / "direct.png"
    fig.savefig(direct, dpi=120, bbox_inches="tight")
    assert path.read_bytes() == direct.read_bytes()
    assert _png_size(path) != (4 * 120, 3 * 120)  # the drawing's size, not the figure's
    # Two formats share one box, found once: the raster is still savefig's to the byte, and
    # the vector picture has the raster's size.
    png, pdf = save_figure(fig, tmp_path / "both", dpi=120)
    assert png.read_bytes() == direct.read_bytes()
    page = re.search(rb"/MediaBox \[ *0 0 ([0-9.]+) ([0-9.]+) *\]", pdf.read_bytes())
    assert page is not None
    width, height = _png_size(png)
    assert float(page[1]) == pytest.approx(width / 120 * 72, abs=1)
    assert float(page[2]) == pytest.approx(height / 120 * 72, abs=1)


def test_a_constrained_figure_is_laid_out_once_for_every_format(tmp_path):
    # Panels, titles and labels laid out by constrained layout (the run pictures): the raster
    # is savefig's own to the byte, the vector picture has the same layout within a fraction of
    # a point, and the figure keeps its layout engine.
    require_module("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    def panels():
        fig = Figure(figsize=(6, 4), layout="constrained")
        FigureCanvasAgg(fig)
        for k, ax in enumerate(fig.subplots(2, 3, sharex=True, sharey=True).flat):
            ax.plot([0, 1000], [0.5, 0.9 - 0.01 * k], label="this robot")
            ax.set_title(f"robot-{k}")
        fig.supxlabel("evaluation")
        fig.suptitle("a run\neach robot's fitness")
        fig.axes[0].legend()
        return fig

    direct = tmp_path / "direct.png"
    panels().savefig(direct, dpi=120)
    fig = panels()
    engine = fig.get_layout_engine()
    png, pdf = save_figure(fig, tmp_path / "both", dpi=120, tight=False)
    assert png.read_bytes() == direct.read_bytes()
    assert pdf.read_bytes().startswith(b"%PDF")
    assert fig.get_layout_engine() is engine
    laid_out = [ax.get_position().bounds for ax in fig.axes]
    fig.savefig(tmp_path / "alone.pdf")  # the PDF's own layout
    width, height = fig.get_size_inches()
    for ours, own in zip(laid_out, (ax.get_position().bounds for ax in fig.axes), strict=True):
        for a, b, size in zip(ours, own, (width, height, width, height), strict=True):
            assert abs(a - b) * size < 0.01  # inches


def test_a_layout_the_engine_cannot_make_or_set_aside_saves_as_savefig_does(tmp_path):
    require_module("matplotlib")
    import matplotlib
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # Axes from two grids: compressed layout cannot lay them out, and matplotlib's draw goes on
    # without it; so does save_figure.
    fig = Figure(layout="compressed")
    FigureCanvasAgg(fig)
    fig.subplots(1, 2)
    fig.add_subplot(fig.add_gridspec(2, 2)[1, 1])
    png, pdf = save_figure(fig, tmp_path / "grids", tight=False)
    assert png.read_bytes().startswith(PNG_MAGIC) and pdf.read_bytes().startswith(b"%PDF")
    # matplotlib's settings ask for tight layout, whose colorbars do not fit the figure's
    # constrained one: the figure keeps its engine and is saved.
    with matplotlib.rc_context({"figure.autolayout": True}):
        fig = Figure(layout="constrained")
        FigureCanvasAgg(fig)
        ax = fig.subplots()
        fig.colorbar(ax.imshow([[0, 1], [1, 0]]))
        engine = fig.get_layout_engine()
        png, pdf = save_figure(fig, tmp_path / "colorbar", tight=False)
        assert fig.get_layout_engine() is engine
    assert png.read_bytes().startswith(PNG_MAGIC) and pdf.read_bytes().startswith(b"%PDF")


def test_suffix_false_writes_exactly_the_path_given(tmp_path):
    target = tmp_path / "world"  # no extension: written as given, in the format asked for
    assert save_figure(_figure(), target, formats=("png",), suffix=False) == [target]
    assert target.read_bytes().startswith(PNG_MAGIC)
    with pytest.raises(ValueError, match="one file"):
        save_figure(_figure(), target, suffix=False)


class _Broken:
    """A figure whose second format fails half-way through drawing."""

    def __init__(self) -> None:
        self.calls = 0
        self.figure = _figure()

    def __getattr__(self, name):
        return getattr(self.figure, name)

    def savefig(self, fname, **kwargs):
        self.calls += 1
        fname.write(b"half a picture")
        if self.calls == 2:
            raise RuntimeError("cannot draw")


def test_a_figure_failing_to_draw_leaves_no_file_and_the_old_one_intact(tmp_path):
    old = tmp_path / "fitness.pdf"
    old.write_bytes(b"the old picture")
    with pytest.raises(RuntimeError, match="cannot draw"):
        save_figure(_Broken(), tmp_path / "fitness")
    # Neither the format drawn nor the one failing: nothing written, no temporary file left.
    assert [p.name for p in tmp_path.iterdir()] == ["fitness.pdf"]
    assert old.read_bytes() == b"the old picture"


def test_an_error_writing_propagates_as_it_is_and_leaves_no_temporary_file(tmp_path):
    (tmp_path / "fitness.png").mkdir()  # a directory in the way: the rename fails
    with pytest.raises(IsADirectoryError):
        save_figure(_figure(), tmp_path / "fitness", formats=("png",))
    assert [p.name for p in tmp_path.iterdir()] == ["fitness.png"]


def test_each_file_goes_through_the_writer_given(tmp_path):
    written: list[tuple[Path, bytes, bool]] = []

    def write(path, data, *, durable):
        written.append((path, data, durable))

    paths = save_figure(_figure(), tmp_path / "x", write=write)
    assert [w[0] for w in written] == paths
    assert all(data for _, data, _ in written) and not any(d for _, _, d in written)
    assert not list(tmp_path.iterdir())
