"""`fmfusion likelihood summarize | calibrate`: the label likelihood summarized from data and fitted
(`workflow`), and the two commands (`commands`)."""
