"""Bar charts as PNG with Pillow alone (a core dependency): `pi0-torch eval`'s success rates with their 95% intervals
(`success.png` beside `eval.json`) and `pi0-torch bench --plot`'s latencies.

```python
>>> image = bar_chart([("Reach", 100.0, 96.3, 100.0), ("PickPlace", 79.0, 70.0, 85.8)], "success, 100 episodes each",
...                   "%", upper=100.0)
>>> image.size[0], image.mode
(900, 'RGB')

```
"""

from __future__ import annotations

from collections.abc import Sequence

from PIL import Image, ImageDraw, ImageFont

WIDTH, ROW, MARGIN = 900, 30, 12
BAR, WHISKER, TEXT, GRID = (70, 110, 180), (20, 20, 20), (20, 20, 20), (225, 225, 225)


def bar_chart(rows: Sequence[tuple[str, float, float | None, float | None]], title: str, unit: str,
              upper: float | None = None) -> Image.Image:
    """Horizontal bars, one per `(label, value, low, high)` row (`low` / `high`: an interval drawn as a whisker, or
    None), with the value written beside each bar; the axis runs from 0 to `upper` (default: the largest value or
    interval end)."""
    font = ImageFont.load_default()
    probe = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    label_width = max([probe.textlength(label, font=font) for label, *_ in rows] + [40.0])
    top = MARGIN + 2 * ROW  # (the title, then the axis's scale)
    height = top + ROW * len(rows) + MARGIN
    image = Image.new("RGB", (WIDTH, height), "white")
    draw = ImageDraw.Draw(image)
    draw.text((MARGIN, MARGIN), title, fill=TEXT, font=font)
    left, right = MARGIN + label_width + 10, WIDTH - MARGIN - 90  # (room for the value's text after the bar)
    ends = [end for _, value, low, high in rows for end in (value, high) if end is not None]
    upper = upper if upper is not None else max(ends + [1e-9])

    def x(value: float) -> float:
        return left + (right - left) * min(max(value, 0.0), upper) / upper

    for tick in range(5):  # the scale: 0, 25, 50, 75, 100% of `upper`
        value = upper * tick / 4
        draw.line([(x(value), top - 6), (x(value), height - MARGIN)], fill=GRID)
        draw.text((x(value) - 10, top - ROW + 6), f"{value:.3g}", fill=TEXT, font=font)
    for index, (label, value, low, high) in enumerate(rows):
        middle = top + ROW * index + ROW / 2
        draw.text((MARGIN, middle - 6), label, fill=TEXT, font=font)
        draw.rectangle([left, middle - 8, max(x(value), left + 1), middle + 8], fill=BAR)
        if low is not None and high is not None:
            draw.line([(x(low), middle), (x(high), middle)], fill=WHISKER, width=2)
            for end in (low, high):
                draw.line([(x(end), middle - 6), (x(end), middle + 6)], fill=WHISKER, width=2)
        interval = f" [{low:.1f}, {high:.1f}]" if low is not None and high is not None else ""
        draw.text((x(max(value, high or value)) + 6, middle - 6), f"{value:.1f}{unit}{interval}", fill=TEXT, font=font)
    return image
