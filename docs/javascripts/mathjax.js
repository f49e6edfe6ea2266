// MathJax for pymdownx.arithmatex (generic mode): $...$ and \(...\) inline, $$...$$ blocks.
window.MathJax = {
  tex: {inlineMath: [["\\(", "\\)"]], displayMath: [["\\[", "\\]"]], processEscapes: true},
  options: {ignoreHtmlClass: ".*|", processHtmlClass: "arithmatex"},
};
