"""A self-contained HTML page that plays a video (WebM embedded as a data URI): how the Snakemake report, which
offers other video files only as downloads, shows an animation in its main pane."""
from __future__ import annotations

import base64
import html
from pathlib import Path

GENERATOR = "pig video page"  # marks a page this module wrote (a stage replaces only its own)
MIME = {".webm": "video/webm", ".mp4": "video/mp4"}


def video_page(video: Path, title: str) -> str:
    """The page: `title` above `video`, looping in a <video> element that fits its pane."""
    video = Path(video)
    if video.suffix.lower() not in MIME:
        raise ValueError(f"{video}: expected a video file ending in {' or '.join(MIME)}")
    try:
        data = base64.b64encode(video.read_bytes()).decode("ascii")
    except OSError as err:
        raise ValueError(f"{video}: cannot read the video ({err.strerror})") from None
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><meta name="generator" content="{GENERATOR}">'
            f"<title>{html.escape(title)}</title><style>body {{ margin: 0; padding: 16px; font: 14px/1.4 system-ui, "
            "sans-serif; color: #1e293b; } h1 { font-size: 16px; margin: 0 0 8px; } video { width: 480px; max-width: 100%; "
            "max-height: 80vh; background: #000; }</style></head>"
            f"<body><h1>{html.escape(title)}</h1>"
            f'<video controls autoplay loop muted playsinline src="data:{MIME[video.suffix.lower()]};base64,{data}">'
            "</video></body></html>\n")


def is_video_page(path: Path) -> bool:
    """Whether `path` is a page `video_page` wrote (so a stage may replace it)."""
    try:
        with open(path, encoding="utf-8", errors="replace") as handle:
            return f'<meta name="generator" content="{GENERATOR}">' in handle.read(400)
    except OSError:
        return False
