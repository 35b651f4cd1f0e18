#pragma once
// A suite that varies what a hospital varies: other heads (subject_anatomy.h),
// large and steep deformations (brain_shift_phantom.h: sinking, retractor,
// midline shift, partial resection with blood, swelling), scanners
// (scanner_model.h: field strength as resolution, SNR and bias; sagittal,
// oblique; T2-like) and a segmentation made by an algorithm from the
// scanner's image (threshold_segmenter.h). Nothing is tuned per case: a case
// is a combination of named parts, deterministic from its seed.
//
// make_hospital_case:
//   1. the phantom on the scanner's grid with no noise (make_phantom): the
//      truth field, its clean labels and the landmarks (intraop point, true
//      preop point of the subject);
//   2. the intraop scene of the deformed subject (intraop_scene.h);
//   3. the scanner's image of it;
//   4. the segmenter's labels from that image, seeded at the subject's
//      left and right ventricle centroids and restricted to the preop brain
//      (plus a margin), both moved by the true rigid head move (what a
//      rigid pre-registration would give it).
#include <string>
#include <vector>

#include "phantom/brain_shift_phantom.h"
#include "phantom/intraop_scene.h"
#include "phantom/scanner_model.h"
#include "phantom/subject_anatomy.h"
#include "phantom/threshold_segmenter.h"

namespace brainshift {

struct HospitalCaseSpec {
  std::string subject;        // a SubjectSpec name of hospital_subjects()
  PhantomSpec deformation;    // name and seed of the case; its grid and noise come from the scanner
  IntraopSceneSpec scene;
  ScannerSpec scanner;
  ThresholdSegmenterSpec segmenter;  // its contrast is the scanner's
};

struct HospitalCase {
  PhantomCase phantom;        // intraop_t1: the scanner image; intraop_labels: the segmenter's
  LabelImage true_labels;     // the noise-free intraop labels on the same grid
  nlohmann::json description; // phantom, scanner, segmentation, and its agreement with the truth
};

// Six subjects: the atlas itself, a small and a large head (scale and
// reshaping), enlarged ventricles (x1.8), hydrocephalus (x2.4 with a
// reshaped head), a tumour's mass effect beside a ventricle; plus one with a
// superficial tumour (a resection target).
std::vector<SubjectSpec> hospital_subjects();
// Thirteen cases over those subjects (see hospital_suite.cpp for each one's why).
std::vector<HospitalCaseSpec> hospital_suite();

HospitalCase make_hospital_case(const Subject& subject, const HospitalCaseSpec& spec);

// Dice of label l between two label maps on one grid.
double label_dice(const LabelImage& a, const LabelImage& b, std::uint16_t l);

}  // namespace brainshift
